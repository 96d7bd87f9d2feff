"""Who is who: key pairs, a robot's contact list, a user's known robots.

Everything lives under a *home* directory (``--home``, ``$TELEBOT_HOME``, or the user's
config dir), so several robots and users can run side by side on one machine::

    <home>/id_telebot          private key (mode 0600):  name = "alice" / private_key = "..."
    <home>/id_telebot.pub      public key, one line:     telebot-x25519 <key> alice
    <home>/contacts.toml       a robot's contacts:       [contacts.alice] public_key, role
    <home>/known_robots.toml   a user's trusted robots:  [robots.guiabot] public_key

Keys are raw 32-byte X25519 keys written as unpadded URL-safe base64 (43 characters),
as in a zenoh key expression they need no escaping.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import os
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey
from cryptography.hazmat.primitives.serialization import Encoding, NoEncryption, PrivateFormat

from telebot.channels.proto.frames import validate_name
from telebot.channels.proto.noise import public_key_of
from telebot.errors import ConfigError, IdentityError

__all__ = [
    "Contact",
    "ContactBook",
    "Identity",
    "KnownRobots",
    "Role",
    "create_paired_homes",
    "decode_key",
    "encode_key",
    "fingerprint",
    "parse_public_key",
]

KEY_FILE = "id_telebot"
PUBLIC_KEY_FILE = "id_telebot.pub"
CONTACTS_FILE = "contacts.toml"
KNOWN_ROBOTS_FILE = "known_robots.toml"
PUBLIC_KEY_PREFIX = "telebot-x25519"


class Role(StrEnum):
    """What a contact may do on a robot."""

    DRIVER = "driver"
    OBSERVER = "observer"
    ADMIN = "admin"


def encode_key(raw: bytes) -> str:
    """A 32-byte key as 43 URL-safe base64 characters, without padding."""
    return base64.urlsafe_b64encode(raw).rstrip(b"=").decode("ascii")


def decode_key(text: str) -> bytes:
    """The 32 bytes of a key written by :func:`encode_key`; ValueError if it is not one."""
    text = text.strip()
    if len(text) != 43:
        raise ValueError(f"a public key is 43 base64 characters, got {len(text)}")
    try:
        raw = base64.urlsafe_b64decode(text + "=")
    except (binascii.Error, ValueError) as exc:
        raise ValueError("a public key is URL-safe base64") from exc
    if len(raw) != 32 or encode_key(raw) != text:
        raise ValueError("not a 32-byte key in canonical base64")
    return raw


def fingerprint(public_key: bytes) -> str:
    """A short form of a public key for people to compare, like ssh's fingerprints."""
    digest = hashlib.sha256(public_key).digest()
    return "SHA256:" + base64.b64encode(digest).decode().rstrip("=")


def _toml_string(value: str) -> str:
    # JSON string escapes are valid TOML basic-string escapes.
    return json.dumps(value, ensure_ascii=False)


def _read_toml(path: Path) -> dict[str, object]:
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {}
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read: {exc}") from exc


def _read_entries(path: Path, section: str) -> Iterator[tuple[str, dict[str, object], str]]:
    """``(name, entry, where)`` for each ``[section.name]`` table of a contacts-like file."""
    data = _read_toml(path)
    unknown = set(data) - {section}
    if unknown:
        raise ConfigError(f"{path}: unknown key {sorted(unknown)[0]!r}")
    table = data.get(section, {})
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: {section!r} must be a table")
    for name, entry in table.items():
        where = f"{path}: {section}.{name}"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where}: must be a table")
        yield name, entry, where


def _write_atomically(path: Path, text: str, mode: int = 0o644) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)  # a stale file would keep its own (maybe wider) mode
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    with os.fdopen(fd, "w", encoding="utf-8") as handle:
        handle.write(text)
    os.replace(tmp, path)


@dataclass(frozen=True)
class Identity:
    """A name and its X25519 key pair: a user or a robot."""

    name: str
    private_key: bytes = field(repr=False)  # never in logs

    @property
    def public_key(self) -> bytes:
        """The raw 32-byte public key."""
        return public_key_of(self.private_key)

    @classmethod
    def generate(cls, name: str) -> Identity:
        """A new random key pair for ``name``."""
        validate_name(name)
        raw = X25519PrivateKey.generate().private_bytes(
            Encoding.Raw, PrivateFormat.Raw, NoEncryption()
        )
        return cls(name, raw)

    def public_line(self) -> str:
        """The ``.pub`` line: ``telebot-x25519 <key> <name>``."""
        return f"{PUBLIC_KEY_PREFIX} {encode_key(self.public_key)} {self.name}"

    def save(self, home: Path, *, overwrite: bool = False) -> Path:
        """Write the key pair under ``home``; refuses to replace an existing key."""
        path = home / KEY_FILE
        if path.exists() and not overwrite:
            raise IdentityError(f"{path} already exists; refusing to overwrite a key")
        body = f"name = {_toml_string(self.name)}\nprivate_key = {_toml_string(encode_key(self.private_key))}\n"
        _write_atomically(path, body, mode=0o600)
        _write_atomically(home / PUBLIC_KEY_FILE, self.public_line() + "\n")
        return path

    @classmethod
    def load(cls, home: Path) -> Identity:
        """Read the key pair under ``home``; IdentityError says what is missing or wrong."""
        path = home / KEY_FILE
        if not path.exists():
            raise IdentityError(f"no key in {home}: create one with the 'keygen' command")
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
            name, key = data["name"], data["private_key"]
            if not isinstance(name, str) or not isinstance(key, str):
                raise TypeError("name and private_key must be strings")
            return cls(validate_name(name), decode_key(key))
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise IdentityError(f"{path}: cannot read: {exc}") from exc
        except (KeyError, TypeError, ValueError) as exc:
            raise IdentityError(f"{path}: not a telebot key file ({exc})") from exc


def parse_public_key(text: str) -> bytes:
    """A public key from its 43-character form or a whole ``.pub`` line."""
    parts = text.split()
    if len(parts) >= 2 and parts[0] == PUBLIC_KEY_PREFIX:
        text = parts[1]
    return decode_key(text)


@dataclass(frozen=True)
class Contact:
    """A user a robot answers, and what they may do."""

    name: str
    public_key: bytes
    role: Role


class ContactBook:
    """A robot's contact list, kept in ``<home>/contacts.toml``."""

    def __init__(self, path: Path, contacts: dict[str, Contact] | None = None) -> None:
        self.path = path
        self._contacts = dict(contacts or {})

    @classmethod
    def load(cls, home: Path) -> ContactBook:
        """Read the contact list (empty when the file does not exist yet)."""
        path = home / CONTACTS_FILE
        contacts: dict[str, Contact] = {}
        for name, entry, where in _read_entries(path, "contacts"):
            if set(entry) - {"public_key", "role"}:
                raise ConfigError(f"{where}: expected only 'public_key' and 'role'")
            try:
                validate_name(name, "contact name")
                key = decode_key(str(entry.get("public_key", "")))
                role = Role(str(entry.get("role", "observer")))
            except ValueError as exc:
                raise ConfigError(f"{where}: {exc}") from exc
            contacts[name] = Contact(name, key, role)
        return cls(path, contacts)

    def save(self) -> None:
        """Write the contact list back."""
        lines = ["# telebot contacts: the users this robot answers, and their roles.\n"]
        for contact in sorted(self._contacts.values(), key=lambda c: c.name):
            lines.append(f"\n[contacts.{_toml_string(contact.name)}]\n")
            lines.append(f"public_key = {_toml_string(encode_key(contact.public_key))}\n")
            lines.append(f"role = {_toml_string(contact.role.value)}\n")
        _write_atomically(self.path, "".join(lines))

    def add(self, name: str, public_key: bytes, role: Role) -> None:
        """Add or replace a contact."""
        validate_name(name, "contact name")
        self._contacts[name] = Contact(name, public_key, role)

    def remove(self, name: str) -> bool:
        """Remove a contact; False when there was none of that name."""
        return self._contacts.pop(name, None) is not None

    def by_key(self, public_key: bytes) -> Contact | None:
        """The contact with that public key, if any."""
        for contact in self._contacts.values():
            if contact.public_key == public_key:
                return contact
        return None

    def __iter__(self) -> Iterator[Contact]:
        return iter(sorted(self._contacts.values(), key=lambda c: c.name))

    def __len__(self) -> int:
        return len(self._contacts)


class KnownRobots:
    """A user's trusted robot keys, kept in ``<home>/known_robots.toml`` (like known_hosts)."""

    def __init__(self, path: Path, robots: dict[str, bytes] | None = None) -> None:
        self.path = path
        self._robots = dict(robots or {})

    @classmethod
    def load(cls, home: Path) -> KnownRobots:
        """Read the known robots (empty when the file does not exist yet)."""
        path = home / KNOWN_ROBOTS_FILE
        robots: dict[str, bytes] = {}
        for name, entry, where in _read_entries(path, "robots"):
            if set(entry) != {"public_key"}:
                raise ConfigError(f"{where}: expected exactly 'public_key'")
            try:
                validate_name(name, "robot name")
                robots[name] = decode_key(str(entry["public_key"]))
            except ValueError as exc:
                raise ConfigError(f"{where}: {exc}") from exc
        return cls(path, robots)

    def save(self) -> None:
        """Write the known robots back."""
        lines = ["# telebot known robots: the robot keys this user trusts.\n"]
        for name, key in sorted(self._robots.items()):
            lines.append(
                f"\n[robots.{_toml_string(name)}]\npublic_key = {_toml_string(encode_key(key))}\n"
            )
        _write_atomically(self.path, "".join(lines))

    def add(self, name: str, public_key: bytes) -> None:
        """Trust ``public_key`` as robot ``name``."""
        validate_name(name, "robot name")
        self._robots[name] = public_key

    def remove(self, name: str) -> bool:
        """Forget a robot; False when it was not known."""
        return self._robots.pop(name, None) is not None

    def get(self, name: str) -> bytes | None:
        """The trusted key of robot ``name``, if any."""
        return self._robots.get(name)

    def names(self) -> list[str]:
        """Names of all known robots."""
        return sorted(self._robots)


def create_paired_homes(
    base: Path, robot: str, user: str, role: Role = Role.DRIVER
) -> tuple[Identity, Identity]:
    """New keys under ``base/robot`` and ``base/user`` that know each other.

    The robot lists the user as a contact with ``role``; the user trusts the robot's key.
    For demos, tests and benchmarks: real files, as ``keygen``, ``contacts add`` and
    ``known add`` would write them.
    """
    robot_identity, user_identity = Identity.generate(robot), Identity.generate(user)
    robot_home, user_home = base / "robot", base / "user"
    robot_identity.save(robot_home)
    user_identity.save(user_home)
    contacts = ContactBook.load(robot_home)
    contacts.add(user, user_identity.public_key, role)
    contacts.save()
    known = KnownRobots.load(user_home)
    known.add(robot, robot_identity.public_key)
    known.save()
    return robot_identity, user_identity
