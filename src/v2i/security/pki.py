"""A site PKI on a directory: the CA issues and revokes, services load what they need.

Layout of the directory (all files written atomically; private keys mode 0600):

    ca.key, ca.cert          the site CA (PKCS#8 PEM key; certificate as in :mod:`.certificates`)
    <subject>.key/.cert      one pair per RSU, vehicle or operator
    revoked.crl              the CA-signed revocation list (absent = nothing revoked)

- :class:`Pki` (``Pki.init(dir, ...)``, ``Pki.load(dir)``) is the CA side: it needs ``ca.key``.
- :func:`load_trust` is what a verifying service loads (CA certificate, revocation list, every
  ``*.cert`` of the directory as a pre-distributed certificate); :func:`load_signer` what a
  signing service loads (its key and certificate). Neither needs the CA key.

Times are arguments (``now_ns``, Unix epoch nanoseconds); nothing here reads a clock. Every
missing, unreadable, corrupt or mismatched file is a :class:`PkiError` naming the file.
"""

from __future__ import annotations

import os
import stat
import time
from dataclasses import dataclass
from pathlib import Path

from v2i.core.files import FileMissing, FileRefused, KiB, MiB, open_regular, read_open
from v2i.security import algorithms as alg
from v2i.security import certificates as certs
from v2i.security.certificates import Certificate, CertificateError, RevocationList

NS_PER_DAY = 86_400 * 10**9
CA_NAME = "ca"
CRL_FILE = "revoked.crl"
# A certificate or private key: ~150-250 bytes (a certificate listing many keys, a few kB).
PKI_FILE_LIMIT_BYTES = 64 * KiB
# The revocation list: ~34 bytes per revoked certificate, so 1 MiB lists ~30,000.
CRL_LIMIT_BYTES = 1 * MiB


class PkiError(RuntimeError):
    """A PKI file or operation that failed; the message names the file and the reason."""


@dataclass(frozen=True)
class Trust:
    """What a verifier trusts: the CA, its revocation list, certificates known in advance."""

    ca: Certificate
    ca_key: alg.PublicKey
    revoked: frozenset[bytes]
    known: dict[bytes, bytes]  # digest -> certificate encoding (checked when first used)


@dataclass(frozen=True)
class Identity:
    """A signer's private key and certificate (the key matches the certificate's public key)."""

    cert: Certificate
    key: alg.PrivateKey


def _write(path: Path, data: bytes, mode: int) -> None:
    """Write ``data`` to ``path`` atomically (temp file + rename), created with ``mode``."""
    tmp = path.with_name(f".{path.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.fchmod(fd, mode)
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)


def read_pki_file(path: Path, what: str, limit_bytes: int = PKI_FILE_LIMIT_BYTES) -> tuple[bytes, int]:
    """The bytes and the mode bits of the regular file ``path`` of at most ``limit_bytes`` (both of
    the one descriptor read: ``v2i.core.files``); PkiError naming the file otherwise."""
    try:
        with open_regular(path, what, limit_bytes) as f:
            return read_open(f, limit_bytes, what, path), stat.S_IMODE(os.fstat(f.fileno()).st_mode)
    except FileMissing:
        raise PkiError(f"{path}: missing {what}") from None
    except FileRefused as exc:
        raise PkiError(str(exc)) from None


def read_cert(path: Path) -> Certificate:
    """The certificate in ``path``; PkiError if missing or corrupt."""
    try:
        return certs.decode(read_pki_file(path, "certificate")[0])
    except CertificateError as exc:
        raise PkiError(f"{path}: corrupt certificate: {exc}") from None


def read_key(path: Path, cert: Certificate) -> alg.PrivateKey:
    """The private key in ``path``, checked to be private (no group/other access) and to match
    ``cert``'s public key; PkiError otherwise."""
    data, mode = read_pki_file(path, "private key")
    if mode & 0o077:
        raise PkiError(f"{path}: private key is accessible by others (mode {mode:04o}); chmod 600 it")
    try:
        key = alg.load_private_pem(data)
    except (ValueError, TypeError) as exc:
        raise PkiError(f"{path}: corrupt private key: {exc}") from None
    if alg.algorithm_of(key) != cert.algorithm or alg.public_bytes(key) != cert.public_key:
        raise PkiError(f"{path}: private key does not match certificate {cert.subject!r}")
    return key


def read_crl(directory: Path, ca: Certificate, ca_key: alg.PublicKey) -> RevocationList | None:
    """``directory``'s revocation list, its CA signature checked; None when absent, PkiError when
    it cannot be read, does not parse or is not signed by ``ca``."""
    path = directory / CRL_FILE
    if not path.exists():
        return None
    try:
        return certs.decode_revocations(read_pki_file(path, "revocation list", CRL_LIMIT_BYTES)[0], ca, ca_key)
    except CertificateError as exc:
        raise PkiError(f"{path}: {exc}") from None


def _load_ca(directory: Path) -> tuple[Certificate, alg.PublicKey]:
    ca = read_cert(directory / f"{CA_NAME}.cert")
    try:
        return ca, certs.check_ca(ca)
    except (CertificateError, ValueError) as exc:
        raise PkiError(f"{directory / f'{CA_NAME}.cert'}: {exc}") from None


def load_trust(directory: str | Path) -> Trust:
    """CA certificate (self-signature checked), revocation list (CA signature checked) and the
    directory's other ``*.cert`` files as known certificates; PkiError on any bad file."""
    directory = Path(directory)
    ca, ca_key = _load_ca(directory)
    crl = read_crl(directory, ca, ca_key)
    known = {}
    for path in sorted(directory.glob("*.cert")):
        if path.name != f"{CA_NAME}.cert":
            cert = read_cert(path)
            known[cert.digest] = cert.encoding
    return Trust(ca, ca_key, crl.revoked if crl else frozenset(), known)


def load_signer(directory: str | Path, subject: str) -> Identity:
    """``<subject>.key`` and ``<subject>.cert`` of ``directory``, checked to belong together."""
    directory = Path(directory)
    cert = read_cert(directory / f"{subject}.cert")
    if cert.role not in certs.SIGNER_ROLES:
        raise PkiError(f"{directory / f'{subject}.cert'}: role {cert.role!r} may not sign messages")
    return Identity(cert, read_key(directory / f"{subject}.key", cert))


def start_warnings(directory: str | Path, now_ns: int, own: str | None = None) -> list[str]:
    """What a service says loudly at start about the PKI in ``directory`` (each a line; [] when
    all is well): private keys that others on the host can read (anyone there can sign as their
    subject: the CA's key, on a service host, should not be there at all); and for ``own``, the
    subject the service signs as, a certificate that is not valid at ``now_ns`` (host clock) or
    that the directory's revocation list revokes: every receiver drops what it signs."""
    directory = Path(directory)
    warnings = []
    for path in sorted(directory.glob("*.key")):
        mode = stat.S_IMODE(os.stat(path).st_mode)
        if mode & 0o077:
            warnings.append(f"{path}: private key readable by others on this host (mode {mode:04o}): "
                            f"anyone here can sign as {path.stem!r}; chmod 600 it"
                            + (" (and keep the CA's key off service hosts)" if path.stem == CA_NAME else ""))
    if own is not None:
        cert = read_cert(directory / f"{own}.cert")
        if not cert.valid_at(now_ns):
            when = "expired" if now_ns > cert.valid_until_ns else "not yet valid"
            warnings.append(f"{directory / f'{own}.cert'}: own certificate {when} (valid "
                            f"{_utc(cert.valid_from_ns)} to {_utc(cert.valid_until_ns)}): every receiver "
                            "will drop what this service signs")
        if (directory / f"{CA_NAME}.cert").exists() and cert.digest in load_trust(directory).revoked:
            warnings.append(f"{directory / f'{own}.cert'}: own certificate revoked by {directory / CRL_FILE}: "
                            "every receiver will drop what this service signs")
    return warnings


def _utc(t_ns: int) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t_ns // 1_000_000_000))


class Pki:
    """The CA side of a site PKI on ``directory``; build with :meth:`init` or :meth:`load`."""

    def __init__(self, directory: Path, ca: Identity) -> None:
        self.directory = directory
        self.ca = ca

    @classmethod
    def init(cls, directory: str | Path, now_ns: int, days: float = 3650, ca_id: str = "site-ca",
             algorithm: str = alg.P256) -> Pki:
        """A new CA in ``directory`` (created if absent), valid ``days`` from ``now_ns``; PkiError
        if the directory already holds a CA."""
        directory = Path(directory)
        if (directory / f"{CA_NAME}.key").exists() or (directory / f"{CA_NAME}.cert").exists():
            raise PkiError(f"{directory}: already holds a CA ({CA_NAME}.key/{CA_NAME}.cert); refusing to overwrite")
        directory.mkdir(parents=True, exist_ok=True)
        key = alg.generate(algorithm)
        until_ns = now_ns + int(days * NS_PER_DAY)
        try:
            cert = certs.build(ca_id, "ca", (), alg.public_bytes(key), algorithm, now_ns, until_ns,
                               certs.SELF_ISSUER, key)
        except CertificateError as exc:
            raise PkiError(f"cannot create CA: {exc}") from None
        _write(directory / f"{CA_NAME}.key", alg.private_pem(key), 0o600)
        _write(directory / f"{CA_NAME}.cert", cert.encoding, 0o644)
        return cls(directory, Identity(cert, key))

    @classmethod
    def load(cls, directory: str | Path) -> Pki:
        """The CA of an existing PKI directory (its key and certificate checked)."""
        directory = Path(directory)
        ca, _ = _load_ca(directory)
        return cls(directory, Identity(ca, read_key(directory / f"{CA_NAME}.key", ca)))

    def issue(self, subject: str, role: str, now_ns: int, keys: tuple[str, ...] | None = None,
              days: float = 365, algorithm: str = alg.P256, replace: bool = False) -> Certificate:
        """Key pair and certificate for ``subject`` (``<subject>.key`` 0600, ``<subject>.cert``),
        valid ``days`` from ``now_ns``, publishing on ``keys`` (default: :func:`default_keys`)."""
        if role not in certs.SIGNER_ROLES:
            raise PkiError(f"cannot issue role {role!r}: expected one of {', '.join(certs.SIGNER_ROLES)}")
        if subject == CA_NAME:
            raise PkiError(f"subject {CA_NAME!r} is reserved for the CA files")
        key_path, cert_path = self.directory / f"{subject}.key", self.directory / f"{subject}.cert"
        if not replace and (key_path.exists() or cert_path.exists()):
            raise PkiError(f"{cert_path}: {subject!r} already has a certificate (replace=True to re-issue)")
        key = alg.generate(algorithm)
        keys = certs.default_keys(role, subject) if keys is None else tuple(keys)
        until_ns = min(now_ns + int(days * NS_PER_DAY), self.ca.cert.valid_until_ns)
        try:
            cert = certs.build(subject, role, keys, alg.public_bytes(key), algorithm, now_ns, until_ns,
                               self.ca.cert.digest, self.ca.key)
        except CertificateError as exc:
            raise PkiError(f"cannot issue {subject!r}: {exc}") from None
        _write(key_path, alg.private_pem(key), 0o600)
        _write(cert_path, cert.encoding, 0o644)
        return cert

    def revoke(self, subject: str, now_ns: int) -> RevocationList:
        """Add ``<subject>.cert``'s digest to the revocation list and re-sign it at ``now_ns``."""
        cert = read_cert(self.directory / f"{subject}.cert")
        if cert.issuer != self.ca.cert.digest:
            raise PkiError(f"{self.directory / f'{subject}.cert'}: not issued by this CA")
        old = read_crl(self.directory, self.ca.cert, self.ca.key.public_key())
        revoked = (old.revoked if old else frozenset()) | {cert.digest}
        crl = certs.sign_revocations(revoked, now_ns, self.ca.cert, self.ca.key)
        _write(self.directory / CRL_FILE, crl.encode(), 0o644)
        return crl
