"""The router's certificate authority: a CA, the router's certificate, client certificates.

A client certificate names its holder in its common name as ``robot:NAME``,
``user:NAME`` or ``admin:NAME`` (``:`` cannot occur in a telebot name, so a robot and a
user of the same name never share one). The router's access control matches these
common names (``telebot.router.acl``).

Layout of a router directory (``telebot-router init DIR``)::

    DIR/ca.pem  DIR/ca.key                      the CA (keep ca.key offline if you can)
    DIR/router.pem  DIR/router.key              the router's certificate (server + client)
    DIR/clients/{kind}-{name}/cert.pem, key.pem, ca.pem   one per robot, user or admin
    DIR/revoked.txt                             common names the ACL no longer lets in
"""

from __future__ import annotations

import datetime
import ipaddress
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Literal

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from telebot.channels.proto.frames import validate_name
from telebot.errors import ConfigError
from telebot.router import acl

__all__ = [
    "KINDS",
    "ClientCert",
    "Kind",
    "check_signed_by",
    "client_dir",
    "common_name",
    "import_client",
    "init_ca",
    "issue_client",
    "list_clients",
    "parse_common_name",
    "read_revoked",
    "revoke",
]

Kind = Literal["robot", "user", "admin"]
#: A CA's key: made here (EC P-256) or brought along (EC or RSA).
CAKey = ec.EllipticCurvePrivateKey | rsa.RSAPrivateKey
KINDS: Final[tuple[Kind, ...]] = ("robot", "user", "admin")
#: Ten years: a CA of one's own; revocation is by the ACL (``revoked.txt``).
_VALIDITY = datetime.timedelta(days=3650)
#: The router certificate's common name (what a linked router's ACL lets in).
ROUTER_CN: Final = acl.ROUTER_CN


@dataclass(frozen=True, slots=True)
class ClientCert:
    """One issued client certificate: who it names and where its files are."""

    kind: Kind
    name: str
    directory: Path

    @property
    def common_name(self) -> str:
        """The certificate's common name, as the ACL matches it."""
        return common_name(self.kind, self.name)

    @property
    def cert(self) -> Path:
        """The certificate (PEM)."""
        return self.directory / "cert.pem"

    @property
    def key(self) -> Path:
        """Its private key (PEM)."""
        return self.directory / "key.pem"

    @property
    def ca(self) -> Path:
        """A copy of the CA certificate, to verify the router."""
        return self.directory / "ca.pem"


def common_name(kind: Kind, name: str) -> str:
    """The common name of ``name``'s certificate, e.g. ``robot:guiabot``."""
    validate_name(name, kind)
    return f"{kind}:{name}"


def parse_common_name(cn: str) -> tuple[Kind, str] | None:
    """``(kind, name)`` of a telebot client common name; None for any other."""
    kind, sep, name = cn.partition(":")
    if not sep or kind not in KINDS:
        return None
    try:
        validate_name(name, kind)
    except ValueError:
        return None
    return kind, name


def client_dir(root: Path, kind: Kind, name: str) -> Path:
    """Where ``name``'s client certificate lives under a router directory."""
    common_name(kind, name)  # validates
    return root / "clients" / f"{kind}-{name}"


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _write_key(path: Path, key: CAKey) -> None:
    data = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as out:
        out.write(data)


def _write_cert(path: Path, cert: x509.Certificate) -> None:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _load_cert(path: Path) -> x509.Certificate:
    try:
        return x509.load_pem_x509_certificate(path.read_bytes())
    except FileNotFoundError as exc:
        raise ConfigError(f"certificate file {path} does not exist") from exc
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path} is not a PEM certificate: {exc}") from exc


def _load_key(path: Path) -> CAKey:
    try:
        key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    except FileNotFoundError as exc:
        raise ConfigError(f"key file {path} does not exist") from exc
    except (OSError, ValueError, TypeError) as exc:
        raise ConfigError(f"{path} is not an unencrypted PEM private key: {exc}") from exc
    if not isinstance(key, ec.EllipticCurvePrivateKey | rsa.RSAPrivateKey):
        raise ConfigError(f"{path}: a CA key must be an EC or RSA key")
    return key


def _builder(
    subject: str, issuer: x509.Name, public: ec.EllipticCurvePublicKey
) -> x509.CertificateBuilder:
    now = datetime.datetime.now(datetime.UTC)
    return (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
        .issuer_name(issuer)
        .public_key(public)
        .serial_number(x509.random_serial_number())
        # An hour back: a client whose clock is a little behind still accepts it.
        .not_valid_before(now - datetime.timedelta(hours=1))
        .not_valid_after(now + _VALIDITY)
    )


def init_ca(
    root: Path,
    hosts: list[str] | None = None,
    *,
    force: bool = False,
    ca: Path | None = None,
    ca_key: Path | None = None,
) -> None:
    """Make ``root`` a router directory: a CA (new, or ``ca`` + ``ca_key``) and the
    router's certificate.

    The router's certificate names 127.0.0.1, ::1, localhost and ``hosts`` (IP
    addresses or DNS names) as subject alternative names. An existing CA is refused
    unless ``force`` (a new CA invalidates every certificate issued so far).
    """
    root.mkdir(parents=True, exist_ok=True)
    if (root / "ca.pem").exists() and not force:
        raise ConfigError(f"{root} already has a CA (ca.pem); use --force to replace it")
    if ca is not None and ca_key is not None:
        _use_ca(root, _load_cert(ca), _load_key(ca_key), hosts)
    else:
        _use_ca(root, None, None, hosts)


def _use_ca(
    root: Path,
    given: x509.Certificate | None,
    given_key: CAKey | None,
    hosts: list[str] | None,
) -> None:
    if given is not None and given_key is not None:
        ca, ca_key = given, given_key
    else:
        ca_key = _new_key()
        ca = _new_ca(ca_key)
    _write_key(root / "ca.key", ca_key)
    _write_cert(root / "ca.pem", ca)
    _router_cert(root, ca, ca_key, hosts)


def _new_ca(ca_key: ec.EllipticCurvePrivateKey) -> x509.Certificate:
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "telebot CA")])
    return (
        _builder("telebot CA", ca_name, ca_key.public_key())
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), False)
        .sign(ca_key, hashes.SHA256())
    )


def _router_cert(root: Path, ca: x509.Certificate, ca_key: CAKey, hosts: list[str] | None) -> None:
    sans: list[x509.GeneralName] = [
        x509.IPAddress(ipaddress.ip_address("127.0.0.1")),
        x509.IPAddress(ipaddress.ip_address("::1")),
        x509.DNSName("localhost"),
    ]
    for host in hosts or []:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            sans.append(x509.DNSName(host))
    key = _new_key()
    cert = (
        _leaf(ROUTER_CN, ca, ca_key, key, server=True)
        .add_extension(x509.SubjectAlternativeName(sans), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    _write_key(root / "router.key", key)
    _write_cert(root / "router.pem", cert)
    (root / "clients").mkdir(exist_ok=True)


def _leaf(
    cn: str,
    ca: x509.Certificate,
    ca_key: CAKey,
    key: ec.EllipticCurvePrivateKey,
    *,
    server: bool,
) -> x509.CertificateBuilder:
    usages = [ExtendedKeyUsageOID.CLIENT_AUTH]
    if server:
        usages.append(ExtendedKeyUsageOID.SERVER_AUTH)
    return (
        _builder(cn, ca.subject, key.public_key())
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), False
        )
    )


def issue_client(root: Path, kind: Kind, name: str, *, force: bool = False) -> ClientCert:
    """Issue a client certificate for ``name`` (a robot, user or admin) under ``root``.

    Issuing again for a revoked name takes it off ``revoked.txt``.
    """
    cn = common_name(kind, name)
    ca = _load_cert(root / "ca.pem")
    ca_key = _load_key(root / "ca.key")
    directory = client_dir(root, kind, name)
    if (directory / "cert.pem").exists() and not force:
        raise ConfigError(f"{directory} already holds a certificate; use --force to replace it")
    directory.mkdir(parents=True, exist_ok=True)
    key = _new_key()
    cert = _leaf(cn, ca, ca_key, key, server=False).sign(ca_key, hashes.SHA256())
    _write_key(directory / "key.pem", key)
    _write_cert(directory / "cert.pem", cert)
    _write_cert(directory / "ca.pem", ca)
    revoked = read_revoked(root)
    if cn in revoked:
        _write_revoked(root, revoked - {cn})
    return ClientCert(kind, name, directory)


def import_client(
    root: Path, kind: Kind, name: str, cert_path: Path, *, force: bool = False
) -> ClientCert:
    """Register an existing certificate for ``name``: it must be issued by ``root``'s CA
    and name ``kind:name``. Only the certificate is copied (its key stays with its owner)."""
    cn = common_name(kind, name)
    check_signed_by(cert_path, root / "ca.pem")
    cert = _load_cert(cert_path)
    names = [a.value for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)]
    if names != [cn]:
        raise ConfigError(f"{cert_path}: common name is {names}, expected {cn!r}")
    directory = client_dir(root, kind, name)
    if (directory / "cert.pem").exists() and not force:
        raise ConfigError(f"{directory} already holds a certificate; use --force to replace it")
    directory.mkdir(parents=True, exist_ok=True)
    _write_cert(directory / "cert.pem", cert)
    _write_cert(directory / "ca.pem", _load_cert(root / "ca.pem"))
    return ClientCert(kind, name, directory)


def list_clients(root: Path) -> list[ClientCert]:
    """Every client certificate issued under ``root``, sorted by kind then name."""
    found: list[ClientCert] = []
    clients = root / "clients"
    if not clients.is_dir():
        return found
    for entry in sorted(clients.iterdir()):
        kind, sep, name = entry.name.partition("-")
        parsed = parse_common_name(f"{kind}:{name}") if sep else None
        if parsed is not None and (entry / "cert.pem").is_file():
            found.append(ClientCert(parsed[0], parsed[1], entry))
    return sorted(found, key=lambda c: (KINDS.index(c.kind), c.name))


def read_revoked(root: Path) -> set[str]:
    """The common names listed in ``root/revoked.txt`` (one a line, ``#`` comments)."""
    path = root / "revoked.txt"
    if not path.exists():
        return set()
    names = set()
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            names.add(line)
    return names


def _write_revoked(root: Path, names: set[str]) -> None:
    text = "# common names the router's ACL no longer lets in (telebot-router revoke)\n"
    (root / "revoked.txt").write_text(text + "".join(f"{n}\n" for n in sorted(names)))


def revoke(root: Path, kind: Kind, name: str) -> str:
    """Add ``name``'s common name to ``revoked.txt``; returns it. Takes effect on restart."""
    cn = common_name(kind, name)
    _write_revoked(root, read_revoked(root) | {cn})
    return cn


def check_signed_by(cert_path: Path, ca_path: Path) -> None:
    """ConfigError unless ``cert_path`` is signed by the CA in ``ca_path``."""
    cert, ca = _load_cert(cert_path), _load_cert(ca_path)
    try:
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature) as exc:
        raise ConfigError(f"certificate {cert_path} is not issued by the CA in {ca_path}") from exc
