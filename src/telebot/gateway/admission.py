"""Who a gateway admits: the router's gateway users, or the robot's contacts and invites.

Router (``telebot-router gateway-user add DIR NAME KEY``)::

    DIR/gateway-users.toml     [users.alice] public_key = "..."

read again at every admission, so adding or removing a user needs no restart; a name
``telebot-router revoke DIR --user NAME`` put in ``DIR/revoked.txt`` is refused (``revoked``).

Robot: its contacts (``<home>/contacts.toml``, the same book the robot answers calls from),
and one-time invites written by ``telebot-robot invite``::

    <home>/invites.json        {"<sha256 of the token, hex>": {"name", "role", "expires", "used"}}

The token itself is only in the link; a redeemed invite is marked used and kept until it
expires. Every change of ``invites.json`` or ``contacts.toml`` (an invite written or
redeemed, ``telebot-robot contacts add/remove``) holds an ``flock`` on ``invites.lock``
beside them (:func:`locked`), so the command line and the running daemon never overwrite
each other's changes.

Both admitters say what their answers depend on (:meth:`Admitter.stamp`: the files' size,
mtime and inode), so a gateway re-checks its open connections only when that changed.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import secrets
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Protocol

from telebot.channels.proto.frames import validate_name
from telebot.errors import ConfigError
from telebot.gateway.core import Refusal
from telebot.identity import CONTACTS_FILE, ContactBook, Role, decode_key, encode_key
from telebot.router.certs import common_name, read_revoked

__all__ = [
    "INVITES_FILE",
    "INVITE_SECONDS",
    "USERS_FILE",
    "Admitter",
    "ContactsAdmitter",
    "GatewayUsers",
    "Invite",
    "UsersAdmitter",
    "contact_key",
    "create_invite",
    "locked",
    "read_invites",
]

USERS_FILE: Final = "gateway-users.toml"
INVITES_FILE: Final = "invites.json"
INVITE_SECONDS: Final = 600.0


class Admitter(Protocol):
    """What a gateway asks about a browser's claimed identity."""

    def key_of(self, name: str) -> bytes | None:
        """The key ``name`` is admitted with, or None; Refusal for a name barred outright
        (``revoked``)."""

    def stamp(self) -> object:
        """Something that changes whenever :meth:`key_of`'s answers may have (cheap: the
        files' ``stat``), so open connections are re-checked only then."""

    def redeem(self, token: str, name: str, key: bytes, now: float) -> None:
        """Register ``key`` as ``name`` with invite ``token`` (wall-clock ``now``); Refusal if
        not; ConfigError or OSError if the files cannot be read or written."""


def _write_atomically(path: Path, text: str, mode: int = 0o600) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    with os.fdopen(fd, "w", encoding="utf-8") as handle:
        handle.write(text)
    os.replace(tmp, path)


def _stat(path: Path) -> tuple[int, int, int] | None:
    try:
        info = path.stat()
    except OSError:
        return None
    return (info.st_ino, info.st_mtime_ns, info.st_size)


# --- the router's user list -------------------------------------------------------------


class GatewayUsers:
    """The router's gateway users: names and keys (``DIR/gateway-users.toml``)."""

    def __init__(self, path: Path, users: dict[str, bytes]) -> None:
        self.path = path
        self.users = users

    @classmethod
    def load(cls, directory: Path) -> GatewayUsers:
        """Read the list (empty when there is no file); ConfigError names a bad entry."""
        path = directory / USERS_FILE
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return cls(path, {})
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"{path}: cannot read: {exc}") from exc
        if set(data) - {"users"} or not isinstance(data.get("users", {}), dict):
            raise ConfigError(f"{path}: expected only [users.NAME] tables")
        users: dict[str, bytes] = {}
        for name, entry in data.get("users", {}).items():
            where = f"{path}: users.{name}"
            if not isinstance(entry, dict) or set(entry) != {"public_key"}:
                raise ConfigError(f"{where}: expected exactly 'public_key'")
            try:
                validate_name(name, "user name")
                users[name] = decode_key(str(entry["public_key"]))
            except ValueError as exc:
                raise ConfigError(f"{where}: {exc}") from exc
        return cls(path, users)

    def save(self) -> None:
        """Write the list back."""
        lines = ["# telebot-router gateway users: who may use the browser gateway.\n"]
        for name, key in sorted(self.users.items()):
            lines.append(f'\n[users."{name}"]\npublic_key = "{encode_key(key)}"\n')
        _write_atomically(self.path, "".join(lines), mode=0o644)


class UsersAdmitter:
    """The router's admission: ``gateway-users.toml``, read again at every admission, less
    the users ``revoked.txt`` names (``user:NAME``, as ``telebot-router revoke`` writes)."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory

    def key_of(self, name: str) -> bytes | None:
        """The key of gateway user ``name``; an unreadable list admits nobody; Refusal
        (``revoked``) for a revoked user."""
        try:
            key = GatewayUsers.load(self.directory).users.get(name)
            revoked = key is not None and common_name("user", name) in read_revoked(self.directory)
        except (ConfigError, OSError, UnicodeDecodeError):
            return None
        if revoked:
            raise Refusal("revoked", f"{name} was revoked on this router")
        return key

    def stamp(self) -> object:
        """The user list's and the revocation list's ``stat``."""
        return (_stat(self.directory / USERS_FILE), _stat(self.directory / "revoked.txt"))

    def redeem(self, token: str, name: str, key: bytes, now: float) -> None:
        """A router has no invites."""
        raise Refusal("no_invites", "this gateway takes no invites (ask for a gateway user)")


# --- the robot's contacts and invites ---------------------------------------------------


@dataclass(frozen=True, slots=True)
class Invite:
    """One invite as stored: who it is for, with what role, until when, whether used."""

    name: str
    role: Role
    expires: float
    used: bool = False
    #: Whether redeeming it may replace an existing contact of that name (``--replace``).
    replace: bool = False


def _token_hash(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


@contextlib.contextmanager
def locked(home: Path) -> Iterator[None]:
    """Hold the lock on ``home``'s ``invites.json`` and ``contacts.toml`` (``invites.lock``)."""
    home.mkdir(parents=True, exist_ok=True)
    fd = os.open(home / "invites.lock", os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing releases the lock


def read_invites(home: Path) -> dict[str, Invite]:
    """The invites by token hash (empty without a file); ConfigError if it is not one."""
    path = home / INVITES_FILE
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return {
            digest: Invite(
                validate_name(str(entry["name"]), "invite name"),
                Role(entry["role"]),
                float(entry["expires"]),
                bool(entry["used"]),
                bool(entry.get("replace", False)),
            )
            for digest, entry in data.items()
        }
    except FileNotFoundError:
        return {}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ConfigError(f"{path}: not an invites file ({exc})") from exc


def _write_invites(home: Path, invites: dict[str, Invite], now: float) -> None:
    # Expired invites are of no use to anyone: they go at the next write.
    data = {
        digest: {
            "name": i.name,
            "role": i.role.value,
            "expires": i.expires,
            "used": i.used,
            "replace": i.replace,
        }
        for digest, i in invites.items()
        if i.expires > now
    }
    _write_atomically(home / INVITES_FILE, json.dumps(data, indent=1) + "\n")


def create_invite(
    home: Path, name: str, role: Role, now: float, *, replace: bool = False
) -> tuple[str, Invite]:
    """A new one-time invite for ``name`` as ``role``, valid :data:`INVITE_SECONDS`;
    ``replace``: its redemption may replace an existing contact ``name`` (else refused).

    Returns the token (for the link only: the file keeps its SHA-256) and the invite.
    """
    validate_name(name, "contact name")
    token = secrets.token_urlsafe(32)
    invite = Invite(name, role, now + INVITE_SECONDS, replace=replace)
    with locked(home):
        invites = read_invites(home)
        invites[_token_hash(token)] = invite
        _write_invites(home, invites, now)
    return token, invite


def contact_key(book: ContactBook, name: str) -> bytes | None:
    """The key of contact ``name`` in ``book``, or None."""
    for contact in book:
        if contact.name == name:
            return contact.public_key
    return None


class ContactsAdmitter:
    """The robot's admission: its contacts (``contacts.toml``, read again at every
    admission, so ``telebot-robot contacts remove`` takes effect at once), and invites
    that add one.

    ``contacts`` is the book the robot answers calls from: a redeemed invite is added to
    ``contacts.toml`` and then to that book through ``hand_over`` (which runs a function
    on the thread that owns the book: the robot's gateway runs on a thread of its own, so
    it never touches the daemon's book itself), so the new contact can call at once,
    without a restart. ``hand_over`` None runs it here (a gateway on the book's own thread).
    """

    def __init__(
        self,
        contacts: ContactBook,
        home: Path,
        *,
        hand_over: Callable[[Callable[[], None]], None] | None = None,
    ) -> None:
        self.contacts = contacts
        self.home = home
        self.hand_over = hand_over if hand_over is not None else (lambda fn: fn())

    def key_of(self, name: str) -> bytes | None:
        """The key of contact ``name`` in ``contacts.toml``; an unreadable book admits nobody."""
        try:
            return contact_key(ContactBook.load(self.home), name)
        except ConfigError:
            return None

    def stamp(self) -> object:
        """``contacts.toml``'s ``stat``."""
        return _stat(self.home / CONTACTS_FILE)

    def redeem(self, token: str, name: str, key: bytes, now: float) -> None:
        """Add ``key`` as contact ``name`` with the invite's role; mark the invite used.

        The invite is marked used before the contact is saved, and marked unused again if
        that fails: a token admits one browser at most, whatever fails when."""
        digest = _token_hash(token)
        with locked(self.home):
            invites = read_invites(self.home)
            invite = invites.get(digest)
            if invite is None:
                raise Refusal("invite_unknown", "no such invite (ask for a new link)")
            if invite.used:
                raise Refusal("invite_used", "this invite was used already (ask for a new link)")
            if invite.expires <= now:
                raise Refusal("invite_expired", "this invite has expired (ask for a new link)")
            if invite.name != name:
                raise Refusal("invite_name", f"this invite is for {invite.name!r}, not {name!r}")
            # The file, read afresh (it may have changed since the daemon started), is the
            # authority; then the daemon's own book, which its calls are answered from.
            book = ContactBook.load(self.home)
            owner = book.by_key(key)
            if owner is not None and owner.name != name:
                raise Refusal("key_in_use", f"this key is contact {owner.name!r} already")
            if not invite.replace and contact_key(book, name) is not None:
                raise Refusal(
                    "name_in_use",
                    f"{name!r} is a contact already and this invite may not replace it",
                )
            invites[digest] = Invite(
                invite.name, invite.role, invite.expires, used=True, replace=invite.replace
            )
            _write_invites(self.home, invites, now)
            try:
                book.add(name, key, invite.role)
                book.save()
            except BaseException:
                invites[digest] = invite
                with contextlib.suppress(OSError):  # then it stays used: never twice
                    _write_invites(self.home, invites, now)
                raise
            role, contacts = invite.role, self.contacts
            # Handed over before the browser hears "admitted": its first HELLO reaches the
            # book's thread after this (call_soon_threadsafe keeps the order).
            self.hand_over(lambda: contacts.add(name, key, role))
