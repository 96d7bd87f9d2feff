"""Classes by name, python-can style: what transports and robot adapters are chosen with.

A :class:`Registry` maps names to classes. Built-in ones are listed as name -> (module,
class) and imported only when asked for (so ``import telebot`` never imports zenoh);
third-party ones are found in an entry-point group. An unknown name is an error that lists
the known ones, and a plug-in that fails to load or is not the right kind of class is an
error that says so, never a crash of the caller.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Generic, TypeVar, cast

from telebot.errors import TelebotError

__all__ = ["Registry"]

T = TypeVar("T")


class Registry(Generic[T]):
    """Named classes of one kind (``what``: "transport", "robot"), built-in and plug-in.

    ``accepts`` checks a loaded plug-in (``shape`` says what it must be, for the error);
    ``error`` is raised for a name that cannot be loaded, ``unknown`` for one nobody knows.
    """

    def __init__(
        self,
        *,
        what: str,
        group: str,
        builtins: Mapping[str, tuple[str, str]],
        accepts: Callable[[object], bool],
        shape: str,
        error: type[TelebotError],
        unknown: type[TelebotError],
    ) -> None:
        self.what = what
        self.group = group
        self.builtins = builtins
        self._accepts = accepts
        self._shape = shape
        self._error = error
        self._unknown = unknown

    def _plugins(self) -> dict[str, EntryPoint]:
        return {ep.name: ep for ep in entry_points(group=self.group)}

    def known(self) -> list[str]:
        """Every name that can be loaded: built-in and installed plug-ins."""
        return sorted(set(self.builtins) | set(self._plugins()))

    def get(self, name: str) -> type[T]:
        """The class registered as ``name``, its module imported on first use."""
        if name in self.builtins:
            module_name, class_name = self.builtins[name]
            try:
                module = importlib.import_module(module_name)
            except ImportError as exc:
                raise self._error(f"{self.what} {name!r} cannot be imported: {exc}") from exc
            return cast(type[T], getattr(module, class_name))
        plugins = self._plugins()
        if name in plugins:
            try:
                cls: Any = plugins[name].load()
            except Exception as exc:  # a broken plug-in must not take the caller down
                raise self._error(f"{self.what} {name!r} failed to load: {exc}") from exc
            if not self._accepts(cls):
                raise self._error(f"{self.what} {name!r} is not {self._shape}")
            return cast(type[T], cls)
        raise self._unknown(
            f"unknown {self.what} {name!r}; known {self.what}s: {', '.join(self.known())}"
        )
