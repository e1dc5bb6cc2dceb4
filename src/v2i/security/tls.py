"""X.509 material for Zenoh TLS and mutual TLS: a site TLS CA and one certificate per node.

Zenoh's ``tls/`` links (rustls) need X.509 certificates, not the compact V2X certificates of
:mod:`.certificates`; this module writes them with ``cryptography.x509``. Layout of the directory:

    tls-ca.pem, tls-ca.key   the site TLS CA (self-signed, ECDSA P-256; key PKCS#8 PEM, mode 0600)
    NAME.pem, NAME.key       one node: CN = NAME, SAN DNS:NAME (+ IP addresses), usable as TLS
                             server and client (mTLS), signed by the CA; key mode 0600

The node's name is its certificate's Common Name, which is what Zenoh's access control matches
(``access_control.subjects[].cert_common_names``): ``rsu``, ``link``, ``obu``, ``operator``, ...
A client that connects to ``tls/HOST:PORT`` checks that HOST is one of the server certificate's
SANs (``transport/link/tls/verify_name_on_connect``), so a node reached by address needs that
address as an IP SAN: ask for ``NAME@IP,IP`` (e.g. ``rsu@10.10.1.1``).

Use a directory of its own (e.g. ``PKI/tls``): a signing PKI (:mod:`.pki`) also writes ``NAME.key``.
Times are arguments (``now_ns``, Unix epoch nanoseconds); nothing here reads a clock. Errors name
the file (:class:`~v2i.security.pki.PkiError`).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import re
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from v2i.security.pki import CA_NAME as SIGNING_CA_NAME
from v2i.security.pki import PkiError
from v2i.security.pki import read_pki_file
from v2i.security.pki import _write as write_atomic

TLS_CA = "tls-ca"
NS_PER_DAY = 86_400 * 10**9
CA_DAYS = 3650.0
BACKDATE_S = 300  # certificates valid from 5 min before now_ns: clocks of the site differ a little
_NAME = re.compile(r"^[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$")
IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address


@dataclass(frozen=True)
class TlsName:
    """One node's certificate request: its Common Name (also a DNS SAN) and its IP SANs."""

    name: str
    ips: tuple[IPAddress, ...] = ()


def parse_name(text: str) -> TlsName:
    """``NAME`` or ``NAME@IP,IP``; ValueError naming the bad part. NAME is a DNS name (letters,
    digits, ``-``, ``.``), since it is also a DNS SAN and a file name."""
    name, _, ips_text = text.partition("@")
    if not _NAME.match(name) or name in (TLS_CA, SIGNING_CA_NAME):
        raise ValueError(f"TLS name {name!r}: must be a DNS name (letters, digits, '-', '.'), not {TLS_CA!r}")
    ips = []
    for part in filter(None, ips_text.split(",")) if ips_text else ():
        try:
            ips.append(ipaddress.ip_address(part.strip()))
        except ValueError:
            raise ValueError(f"TLS name {text!r}: {part!r} is not an IP address") from None
    if "@" in text and not ips:
        raise ValueError(f"TLS name {text!r}: no IP address after '@'")
    return TlsName(name, tuple(ips))


def _utc(t_ns: int) -> dt.datetime:
    return dt.datetime.fromtimestamp(t_ns / 1e9, tz=dt.timezone.utc)


def _pem_key(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _builder(subject: str, issuer: x509.Name, public_key, now_ns: int, days: float) -> x509.CertificateBuilder:
    """Subject, issuer, key, serial and validity [now - BACKDATE_S, now + days] of a certificate."""
    not_before_ns = now_ns - BACKDATE_S * 10**9
    return (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
            .issuer_name(issuer).public_key(public_key).serial_number(x509.random_serial_number())
            .not_valid_before(_utc(not_before_ns)).not_valid_after(_utc(now_ns + int(days * NS_PER_DAY))))


def _new_ca(directory: Path, now_ns: int) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A self-signed CA (basicConstraints CA, keyCertSign), written as tls-ca.pem / tls-ca.key."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "v2i site TLS CA")])
    builder = _builder("v2i site TLS CA", name, key.public_key(), now_ns, CA_DAYS)
    cert = (builder.add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    write_atomic(directory / f"{TLS_CA}.key", _pem_key(key), 0o600)
    write_atomic(directory / f"{TLS_CA}.pem", cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return key, cert


def _load_ca(directory: Path) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """The CA's key and certificate; PkiError naming the file when missing, open to others,
    corrupt or not a pair."""
    key_path, cert_path = directory / f"{TLS_CA}.key", directory / f"{TLS_CA}.pem"
    for path in (key_path, cert_path):
        if not path.exists():
            raise PkiError(f"{path}: missing (the TLS CA has only one of its two files)")
    key_pem, mode = read_pki_file(key_path, "private key")
    if mode & 0o077:
        raise PkiError(f"{key_path}: private key is accessible by others (mode {mode:04o}); chmod 600 it")
    try:
        key = serialization.load_pem_private_key(key_pem, password=None)
    except (ValueError, TypeError) as exc:
        raise PkiError(f"{key_path}: corrupt private key: {exc}") from None
    try:
        cert = x509.load_pem_x509_certificate(read_pki_file(cert_path, "certificate")[0])
    except ValueError as exc:
        raise PkiError(f"{cert_path}: corrupt certificate: {exc}") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey) or key.public_key() != cert.public_key():
        raise PkiError(f"{key_path}: private key does not match certificate {cert_path}")
    return key, cert


def _issue(directory: Path, request: TlsName, ca_key, ca_cert: x509.Certificate, now_ns: int,
           days: float) -> list[Path]:
    """NAME.key (0600) and NAME.pem: CN and DNS SAN NAME, IP SANs, serverAuth + clientAuth."""
    key = ec.generate_private_key(ec.SECP256R1())
    sans = [x509.DNSName(request.name), *(x509.IPAddress(ip) for ip in request.ips)]
    cert = (_builder(request.name, ca_cert.subject, key.public_key(), now_ns, days)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(True, False, False, False, False, False, False, False, False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))
    key_path, cert_path = directory / f"{request.name}.key", directory / f"{request.name}.pem"
    write_atomic(key_path, _pem_key(key), 0o600)
    write_atomic(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return [cert_path, key_path]


def issue_tls(directory: str | Path, names, now_ns: int, days: float = 30.0) -> list[Path]:
    """Write the site TLS CA into ``directory`` if absent, then a certificate and key for every
    name (``NAME`` or ``NAME@IP,IP``, see :func:`parse_name`; re-issued if present), valid ``days``
    from ``now_ns``. Returns the paths written (CA first when created). PkiError naming the file
    on a bad CA or a directory that holds a signing PKI; ValueError on a bad name or ``days``."""
    directory = Path(directory)
    requests = [parse_name(n) for n in names]
    if not days > 0:
        raise ValueError(f"days must be > 0, got {days}")
    signing_ca = directory / f"{SIGNING_CA_NAME}.cert"
    if signing_ca.exists():
        raise PkiError(f"{signing_ca}: {directory} holds a signing PKI (its NAME.key files would be "
                       f"overwritten); give TLS a directory of its own, e.g. {directory}/tls")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PkiError(f"{directory}: cannot create the directory: {exc.strerror}") from None
    written: list[Path] = []
    if not (directory / f"{TLS_CA}.key").exists() and not (directory / f"{TLS_CA}.pem").exists():
        _new_ca(directory, now_ns)
        written += [directory / f"{TLS_CA}.pem", directory / f"{TLS_CA}.key"]
    ca_key, ca_cert = _load_ca(directory)
    for request in requests:
        written += _issue(directory, request, ca_key, ca_cert, now_ns, days)
    return written
