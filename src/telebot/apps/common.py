"""What both command lines share: argument parsing, config, homes, one-line errors."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Coroutine, Iterator
from pathlib import Path
from typing import Any, Literal, NoReturn, TypeVar

from pydantic import ValidationError

from telebot import __version__
from telebot.channels.proto.frames import validate_name
from telebot.channels.transports import apply_cli_option, declared_cli_options
from telebot.config import AppConfig, default_home, format_validation_error, load_toml
from telebot.errors import (
    CallError,
    ConfigError,
    IdentityError,
    RobotUnreachable,
    TelebotError,
    TransportError,
)
from telebot.identity import Identity

__all__ = [
    "EXIT_FAILURE",
    "EXIT_OK",
    "EXIT_USAGE",
    "THREAD_EXIT_WAIT",
    "ZENOH_THREAD_PREFIX",
    "Parser",
    "add_connection_options",
    "add_home_option",
    "add_log_level_option",
    "app_config",
    "finish_threads",
    "home_of",
    "keygen",
    "load_app_config",
    "name_arg",
    "new_parser",
    "run",
    "stop_on_signals",
]

Config = TypeVar("Config", bound=AppConfig)

EXIT_OK = 0
EXIT_FAILURE = 1  # the command ran but what it asked for failed
EXIT_USAGE = 2  # bad flags, config or keys; or no connection


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line and exit 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see --help)\n")


LOG_LEVELS = ["debug", "info", "warning", "error"]


def new_parser(prog: str, description: str) -> Parser:
    """The top-level parser of a telebot command, with --version and --log-level."""
    parser = Parser(prog=prog, description=description)
    parser.add_argument("--version", action="version", version=f"{prog} {__version__}")
    parser.add_argument(
        "--log-level",
        default="warning",
        type=str.lower,
        choices=LOG_LEVELS,
        help="logging threshold (default: warning)",
    )
    return parser


def add_log_level_option(parser: argparse.ArgumentParser) -> None:
    """``--log-level`` after a sub-command too (``telebot-robot run --log-level info``)."""
    parser.add_argument(
        "--log-level",
        default=argparse.SUPPRESS,  # keep the top-level value unless given here
        type=str.lower,
        choices=LOG_LEVELS,
        help="logging threshold (default: warning)",
    )


def name_arg(text: str) -> str:
    """argparse type of robot and user names (they become zenoh key chunks)."""
    try:
        return validate_name(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def add_home_option(parser: argparse.ArgumentParser, kind: Literal["robot", "user"]) -> None:
    """``--home``: where keys and contact lists live."""
    parser.add_argument(
        "--home",
        type=Path,
        default=None,
        help=f"directory of keys and contact lists (default: $TELEBOT_HOME or {default_home(kind)})",
    )


def add_connection_options(parser: argparse.ArgumentParser) -> None:
    """``--config`` and the flags the transports declare (zenoh's ``--listen``,
    ``--connect``): how to reach the network."""
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="TOML config file (see configs/); default: built-in defaults",
    )
    for _, option in declared_cli_options():
        parser.add_argument(
            option.flag,
            action="append" if option.repeatable else "store",
            default=[] if option.repeatable else None,
            metavar=option.metavar,
            help=option.help,
        )


def home_of(args: argparse.Namespace, kind: Literal["robot", "user"]) -> Path:
    """The home directory chosen by ``--home``, ``$TELEBOT_HOME`` or the default."""
    home: Path | None = args.home
    return home.expanduser() if home is not None else default_home(kind)


def app_config(args: argparse.Namespace) -> AppConfig:
    """The config file (or defaults) with ``--listen`` / ``--connect`` applied."""
    return load_app_config(args, AppConfig)


def load_app_config(args: argparse.Namespace, model: type[Config]) -> Config:
    """``--config`` read as ``model`` (or its defaults), with the transports' flags
    (``--listen`` / ``--connect``) given on the command line applied over it."""
    config = load_toml(args.config, model) if args.config else model()
    try:
        for name, option in declared_cli_options():
            value = getattr(args, option.flag.lstrip("-").replace("-", "_"), None)
            if value:  # not given: the config file's value stands
                apply_cli_option(config.transport, name, option, value)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, "command line")) from exc
    return config


EXIT_TERMINATED = 128 + signal.SIGTERM


async def _terminable(main: Callable[[], Coroutine[Any, Any, int]]) -> int:
    """Run ``main``; SIGTERM cancels it, so its ``async with`` blocks hang up and close."""
    task = asyncio.current_task()
    assert task is not None
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGTERM, task.cancel)
    try:
        return await main()
    except asyncio.CancelledError:
        return EXIT_TERMINATED
    finally:
        loop.remove_signal_handler(signal.SIGTERM)


@contextlib.contextmanager
def stop_on_signals(stop: asyncio.Event) -> Iterator[None]:
    """Inside the block, SIGINT and SIGTERM set ``stop`` (a server's clean shutdown).

    Call it from a coroutine on the running loop; the handlers are removed on the way out.
    """
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        yield
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)


def keygen(name: str, home: Path, *, overwrite: bool, kind: Literal["robot", "user"]) -> int:
    """``keygen``: write a new key pair under ``home`` and print its public line."""
    identity = Identity.generate(name)
    identity.save(home, overwrite=overwrite)
    print(f"{kind} key of {identity.name} written to {home}")
    print(identity.public_line())
    return EXIT_OK


#: Threads the zenoh transport starts (reader, close, late close) are named so.
ZENOH_THREAD_PREFIX = "zenoh-"
#: How long a command waits at exit for those threads to leave zenoh (s).
THREAD_EXIT_WAIT = 3.0


def run(prog: str, main: Callable[[], Coroutine[Any, Any, int]], log_level: str) -> int:
    """Run ``main`` on a new event loop; turn telebot errors into one line and an exit code.

    Before returning, waits for the transport's threads to end (:func:`finish_threads`);
    if one is still inside zenoh after :data:`THREAD_EXIT_WAIT`, the process exits at
    once with the code rather than let the interpreter shut down under it.
    """
    logging.basicConfig(
        level=log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    code = _run(prog, main)
    if not finish_threads(THREAD_EXIT_WAIT):
        # A thread still inside zenoh that wakes up while the interpreter finalizes is
        # killed there, which aborts the process ("FATAL: exception not rethrown",
        # SIGABRT) instead of exiting with the code: skip the finalization.
        logging.getLogger("telebot").warning("zenoh did not finish closing; exiting anyway")
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


def _run(prog: str, main: Callable[[], Coroutine[Any, Any, int]]) -> int:
    try:
        return asyncio.run(_terminable(main))
    except KeyboardInterrupt:
        return 130
    # A robot that is not there (no ROS 2 router, no Nav2) is "no connection": exit 2.
    except (ConfigError, IdentityError, TransportError, CallError, RobotUnreachable) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except TelebotError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_FAILURE


def finish_threads(timeout: float) -> bool:
    """Wait up to ``timeout`` s for the zenoh transport's threads; True if none is left.

    Closing a transport hands the zenoh calls to daemon threads and may return before they
    end (the close timed out, or the thread is still releasing the session after handing
    back its result). The interpreter must not finalize while one of them can still come
    back from zenoh and ask for the GIL.
    """
    deadline = time.monotonic() + timeout
    for thread in threading.enumerate():
        if thread.name.startswith(ZENOH_THREAD_PREFIX) and thread is not threading.current_thread():
            thread.join(max(0.0, deadline - time.monotonic()))
    return not any(
        thread.is_alive() and thread.name.startswith(ZENOH_THREAD_PREFIX)
        for thread in threading.enumerate()
    )
