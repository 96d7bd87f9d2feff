"""HTTPS for the gateway: a server SSL context, and a robot's own self-signed certificate.

A browser needs a secure context for the camera, the microphone and WebCodecs, so the
gateway serves HTTPS only (plain HTTP only on a loopback address, for tests). A robot
without a certificate of its own (``[gateway] cert``/``key``) gets a self-signed one under
its home, made once: ``<home>/gateway/cert.pem`` and ``key.pem``.
"""

from __future__ import annotations

import datetime
import ipaddress
import logging
import socket
import ssl
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from telebot.errors import ConfigError

__all__ = ["local_hosts", "self_signed", "server_certificate", "server_context"]

log = logging.getLogger(__name__)


def server_context(cert: Path, key: Path) -> ssl.SSLContext:
    """An HTTPS server context with ``cert`` (PEM, may hold the chain) and ``key``."""
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    try:
        context.load_cert_chain(str(cert), str(key))
    except (OSError, ssl.SSLError) as exc:
        raise ConfigError(f"gateway certificate {cert} / key {key}: {exc}") from exc
    return context


def local_hosts() -> list[str]:
    """Names and addresses a browser on this machine's networks may use to reach it."""
    hosts = ["localhost", "127.0.0.1", "::1"]
    name = socket.gethostname()
    hosts += [name, f"{name}.local"]
    try:
        # The address of the interface towards other hosts (no packet is sent).
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.connect(("192.0.2.1", 9))
            hosts.append(probe.getsockname()[0])
    except OSError:
        pass
    return list(dict.fromkeys(hosts))


def server_certificate(
    common_name: str, hosts: list[str], valid: datetime.timedelta
) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """A self-signed server certificate (ECDSA P-256) for ``hosts`` (names or addresses),
    valid from five minutes ago for ``valid``, and its new key."""
    key = ec.generate_private_key(ec.SECP256R1())
    names: list[x509.GeneralName] = []
    for host in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            names.append(x509.DNSName(host))
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + valid)
        .add_extension(x509.SubjectAlternativeName(names), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .sign(key, hashes.SHA256())
    )
    return cert, key


def self_signed(directory: Path, hosts: list[str]) -> tuple[Path, Path, bool]:
    """``directory/cert.pem`` and ``key.pem``, made (self-signed, ten years) if missing.

    Returns the two paths and whether they were made now.
    """
    cert_path, key_path = directory / "cert.pem", directory / "key.pem"
    if cert_path.is_file() and key_path.is_file():
        return cert_path, key_path, False
    directory.mkdir(parents=True, exist_ok=True)
    cert, key = server_certificate("telebot robot gateway", hosts, datetime.timedelta(days=3650))
    key_path.write_bytes(b"")
    key_path.chmod(0o600)
    key_path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return cert_path, key_path, True
