"""Key pairs, the robot's contact book and the user's known robots."""

from __future__ import annotations

import base64
import stat
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from telebot.channels.proto.noise import public_key_of
from telebot.errors import ConfigError, IdentityError
from telebot.identity import (
    Contact,
    ContactBook,
    Identity,
    KnownRobots,
    Role,
    decode_key,
    encode_key,
    fingerprint,
    parse_public_key,
)

KEY_A = bytes(range(32))
KEY_B = bytes(range(32, 64))
ALPHABET = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_"


# --------------------------------------------------------------------------- keys


@settings(max_examples=100, deadline=None)
@given(raw=st.binary(min_size=32, max_size=32))
def test_key_encoding_round_trip(raw: bytes) -> None:
    text = encode_key(raw)
    assert len(text) == 43
    assert set(text) <= set(ALPHABET)
    assert decode_key(text) == raw
    assert decode_key(f"  {text}\n") == raw
    assert parse_public_key(text) == raw


@pytest.mark.parametrize("size", [0, 1, 16, 31, 33, 64])
def test_decode_key_rejects_wrong_lengths(size: int) -> None:
    text = base64.urlsafe_b64encode(bytes(size)).rstrip(b"=").decode()
    with pytest.raises(ValueError, match="43"):
        decode_key(text)


def test_decode_key_rejects_padded_and_wrong_length_text() -> None:
    text = encode_key(KEY_A)
    for bad in (text + "=", text[:-1], text + "A", ""):
        with pytest.raises(ValueError, match="43"):
            decode_key(bad)


def test_decode_key_rejects_non_canonical_base64() -> None:
    text = encode_key(KEY_A)
    # The last character carries 2 unused bits; setting one gives the same bytes...
    last = ALPHABET.index(text[-1])
    assert last & 0b11 == 0
    sloppy = text[:-1] + ALPHABET[last | 0b01]
    assert base64.urlsafe_b64decode(sloppy + "=") == KEY_A
    # ...but is not the canonical form, so it is refused.
    with pytest.raises(ValueError, match="canonical"):
        decode_key(sloppy)


def test_decode_key_rejects_other_alphabets_and_characters() -> None:
    key = bytes([0xFB, 0xFF] * 16)  # encodes to '-' and '_' in URL-safe base64
    text = encode_key(key)
    assert "-" in text
    assert "_" in text
    standard = text.replace("-", "+").replace("_", "/")
    for bad in (standard, "!" + text[1:], text[:20] + " " + text[21:], "é" * 43):
        with pytest.raises(ValueError):  # noqa: PT011 - messages differ by cause
            decode_key(bad)


def test_parse_public_key_accepts_pub_lines() -> None:
    text = encode_key(KEY_A)
    assert parse_public_key(f"telebot-x25519 {text} alice") == KEY_A
    assert parse_public_key(f"telebot-x25519 {text}") == KEY_A
    with pytest.raises(ValueError, match="43"):
        parse_public_key(f"ssh-ed25519 {text} alice")


def test_fingerprint() -> None:
    fp = fingerprint(KEY_A)
    assert fp.startswith("SHA256:")
    assert len(fp) == len("SHA256:") + 43
    assert fp == fingerprint(KEY_A)
    assert fp != fingerprint(KEY_B)


# --------------------------------------------------------------------------- identities


def test_generate_gives_distinct_valid_key_pairs() -> None:
    a, b = Identity.generate("alice"), Identity.generate("alice")
    assert len(a.private_key) == 32
    assert a.private_key != b.private_key
    assert a.public_key == public_key_of(a.private_key)
    assert len(a.public_key) == 32


@pytest.mark.parametrize("name", ["", "bad name", "a/b", "-x", "x" * 65])
def test_generate_refuses_bad_names(name: str) -> None:
    with pytest.raises(ValueError, match="invalid name"):
        Identity.generate(name)


def test_save_load_round_trip(tmp_path: Path) -> None:
    home = tmp_path / "home" / "alice"  # created on save
    identity = Identity.generate("alice")
    path = identity.save(home)
    assert path == home / "id_telebot"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert Identity.load(home) == identity
    assert not list(home.glob("*.tmp"))


def test_pub_file_line_format(tmp_path: Path) -> None:
    identity = Identity.generate("guiabot")
    identity.save(tmp_path)
    text = (tmp_path / "id_telebot.pub").read_text()
    assert text.endswith("\n")
    assert text.count("\n") == 1
    prefix, key, name = text.split()
    assert (prefix, name) == ("telebot-x25519", "guiabot")
    assert decode_key(key) == identity.public_key
    assert text.rstrip("\n") == identity.public_line()
    assert parse_public_key(text) == identity.public_key
    # The public file does not carry the private key.
    assert encode_key(identity.private_key) not in text


def test_save_refuses_to_overwrite(tmp_path: Path) -> None:
    first, second = Identity.generate("alice"), Identity.generate("alice")
    first.save(tmp_path)
    with pytest.raises(IdentityError, match="refusing to overwrite"):
        second.save(tmp_path)
    assert Identity.load(tmp_path) == first
    second.save(tmp_path, overwrite=True)
    assert Identity.load(tmp_path) == second
    assert stat.S_IMODE((tmp_path / "id_telebot").stat().st_mode) == 0o600
    assert parse_public_key((tmp_path / "id_telebot.pub").read_text()) == second.public_key


def test_load_without_a_key(tmp_path: Path) -> None:
    with pytest.raises(IdentityError, match="keygen"):
        Identity.load(tmp_path)


@pytest.mark.parametrize(
    "body",
    [
        "name = 'alice'\n",
        "private_key = 'x'\n",
        "name = 'alice'\nprivate_key = 'tooshort'\n",
        "name = 'bad name'\nprivate_key = '" + encode_key(KEY_A) + "'\n",
        "name = 1\nprivate_key = '" + encode_key(KEY_A) + "'\n",
        "not toml at all [\n",
    ],
)
def test_load_malformed_key_file(tmp_path: Path, body: str) -> None:
    (tmp_path / "id_telebot").write_text(body)
    with pytest.raises(IdentityError, match="id_telebot"):
        Identity.load(tmp_path)


# --------------------------------------------------------------------------- contact book


def test_contact_book_round_trip(tmp_path: Path) -> None:
    book = ContactBook.load(tmp_path)  # no file yet: empty
    assert len(book) == 0
    book.add("alice", KEY_A, Role.DRIVER)
    book.add("bob.k-9_x", KEY_B, Role.OBSERVER)
    book.add("carol", bytes(32), Role.ADMIN)
    book.save()
    assert (tmp_path / "contacts.toml").exists()

    loaded = ContactBook.load(tmp_path)
    assert list(loaded) == [
        Contact("alice", KEY_A, Role.DRIVER),
        Contact("bob.k-9_x", KEY_B, Role.OBSERVER),
        Contact("carol", bytes(32), Role.ADMIN),
    ]
    assert len(loaded) == 3
    assert loaded.by_key(KEY_B) == Contact("bob.k-9_x", KEY_B, Role.OBSERVER)
    assert loaded.by_key(b"\x07" * 32) is None


def test_contact_book_add_replace_remove(tmp_path: Path) -> None:
    book = ContactBook.load(tmp_path)
    book.add("alice", KEY_A, Role.OBSERVER)
    book.add("alice", KEY_B, Role.DRIVER)  # replaces
    assert len(book) == 1
    assert book.by_key(KEY_A) is None
    assert book.by_key(KEY_B) == Contact("alice", KEY_B, Role.DRIVER)
    assert book.remove("alice")
    assert not book.remove("alice")
    with pytest.raises(ValueError, match="contact name"):
        book.add("bad name", KEY_A, Role.DRIVER)
    book.save()
    assert len(ContactBook.load(tmp_path)) == 0


def test_contact_role_defaults_to_observer(tmp_path: Path) -> None:
    (tmp_path / "contacts.toml").write_text(
        f'[contacts.alice]\npublic_key = "{encode_key(KEY_A)}"\n'
    )
    assert list(ContactBook.load(tmp_path)) == [Contact("alice", KEY_A, Role.OBSERVER)]


@pytest.mark.parametrize(
    ("body", "names"),
    [
        ("robots = {}\n", ["unknown key 'robots'"]),
        ("contacts = 3\n", ["'contacts' must be a table"]),
        (
            '[contacts.alice]\npublic_key = "{KEY}"\nrole = "superuser"\n',
            ["contacts.alice", "superuser"],
        ),
        ('[contacts.alice]\npublic_key = "not-a-key"\nrole = "driver"\n', ["contacts.alice", "43"]),
        ('[contacts.alice]\nrole = "driver"\n', ["contacts.alice"]),
        (
            '[contacts.alice]\npublic_key = "{KEY}"\nrole = "driver"\ncolour = "red"\n',
            ["contacts.alice", "expected only"],
        ),
        ('[contacts."bad name"]\npublic_key = "{KEY}"\n', ["contacts.bad name", "contact name"]),
        ("contacts.alice = 5\n", ["contacts.alice"]),
        ("[contacts\n", ["cannot read"]),
    ],
    ids=[
        "unknown-key",
        "not-a-table",
        "bad-role",
        "bad-key",
        "missing-key",
        "extra-field",
        "bad-name",
        "entry-not-table",
        "bad-toml",
    ],
)
def test_contact_book_errors_name_file_and_key(tmp_path: Path, body: str, names: list[str]) -> None:
    path = tmp_path / "contacts.toml"
    path.write_text(body.replace("{KEY}", encode_key(KEY_A)))
    with pytest.raises(ConfigError) as info:
        ContactBook.load(tmp_path)
    message = str(info.value)
    assert str(path) in message
    for name in names:
        assert name in message
    assert isinstance(info.value, ValueError)


# --------------------------------------------------------------------------- known robots


def test_known_robots_round_trip(tmp_path: Path) -> None:
    robots = KnownRobots.load(tmp_path)
    assert robots.names() == []
    robots.add("guiabot", KEY_A)
    robots.add("arm.2", KEY_B)
    robots.save()

    loaded = KnownRobots.load(tmp_path)
    assert loaded.names() == ["arm.2", "guiabot"]
    assert loaded.get("guiabot") == KEY_A
    assert loaded.get("arm.2") == KEY_B
    assert loaded.get("nobody") is None
    assert loaded.remove("arm.2")
    assert not loaded.remove("arm.2")
    loaded.save()
    assert KnownRobots.load(tmp_path).names() == ["guiabot"]
    with pytest.raises(ValueError, match="robot name"):
        loaded.add("a*b", KEY_A)


@pytest.mark.parametrize(
    ("body", "names"),
    [
        ("contacts = {}\n", ["unknown key 'contacts'"]),
        ('robots = "x"\n', ["'robots' must be a table"]),
        ('[robots.guiabot]\npublic_key = "short"\n', ["robots.guiabot", "43"]),
        ("[robots.guiabot]\n", ["robots.guiabot", "exactly 'public_key'"]),
        (
            '[robots.guiabot]\npublic_key = "{KEY}"\nrole = "driver"\n',
            ["robots.guiabot", "exactly 'public_key'"],
        ),
        ('[robots."bad/name"]\npublic_key = "{KEY}"\n', ["robots.bad/name", "robot name"]),
        ("robots = [\n", ["cannot read"]),
    ],
    ids=[
        "unknown-key",
        "not-a-table",
        "bad-key",
        "missing-key",
        "extra-field",
        "bad-name",
        "bad-toml",
    ],
)
def test_known_robots_errors_name_file_and_key(tmp_path: Path, body: str, names: list[str]) -> None:
    path = tmp_path / "known_robots.toml"
    path.write_text(body.replace("{KEY}", encode_key(KEY_A)))
    with pytest.raises(ConfigError) as info:
        KnownRobots.load(tmp_path)
    message = str(info.value)
    assert str(path) in message
    for name in names:
        assert name in message


def test_known_robots_rejects_non_canonical_key(tmp_path: Path) -> None:
    text = encode_key(KEY_A)
    sloppy = text[:-1] + ALPHABET[ALPHABET.index(text[-1]) | 1]
    path = tmp_path / "known_robots.toml"
    path.write_text(f'[robots.guiabot]\npublic_key = "{sloppy}"\n')
    with pytest.raises(ConfigError, match="canonical") as info:
        KnownRobots.load(tmp_path)
    assert str(path) in str(info.value)


def test_stale_temp_file_does_not_widen_the_private_key_mode(tmp_path: Path) -> None:
    stale = tmp_path / "id_telebot.tmp"
    stale.write_text("old")
    stale.chmod(0o644)
    Identity.generate("alice").save(tmp_path)
    assert (tmp_path / "id_telebot").stat().st_mode & 0o777 == 0o600


def test_repr_of_an_identity_hides_the_private_key() -> None:
    identity = Identity.generate("alice")
    assert identity.private_key.hex() not in repr(identity)
    assert repr(identity.private_key) not in repr(identity)
