"""Site certificates and the revocation list: small signed msgpack structures.

Modelled on IEEE 1609.2 / ETSI TS 103 097 explicit certificates, in spirit, not in ASN.1:

    certificate = [version, subject_id, role, keys, algorithm, public_key,
                   valid_from_ns, valid_until_ns, issuer, signature]

- ``role``: ``ca`` | ``rsu`` | ``vehicle`` | ``operator``; only the CA (self-signed, ``issuer`` =
  eight zero bytes, 1609.2's ``self``) signs certificates and revocation lists, and a CA
  certificate never signs a message.
- ``keys``: the Zenoh key expressions the holder may publish on (1609.2's ``appPermissions``);
  ``*`` stands for one chunk, ``**`` for any number of chunks (see :func:`covers`).
- ``issuer``: the CA certificate's digest; ``signature``: the CA's, over the msgpack encoding of
  the first nine fields (the "to be signed" part).
- digest (1609.2 ``HashedId8``): the low-order eight bytes of SHA-256 over the whole encoding,
  i.e. its last eight bytes in network byte order, as 1609.2 6.3.34 defines it.

    revocation list = [version, issuer, issued_ns, revoked digests (sorted), signature]

signed by the CA over the first four fields. Decoding validates every field (types, lengths,
ranges) and raises :class:`CertificateError` (a ValueError) naming what is wrong.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field

import msgpack

from v2i.security import algorithms as alg

VERSION = 1
ROLES = ("ca", "rsu", "vehicle", "operator")
SIGNER_ROLES = ("rsu", "vehicle", "operator")
DIGEST_BYTES = 8
SELF_ISSUER = bytes(DIGEST_BYTES)
MAX_KEYS = 16
MAX_KEY_CHARS = 200
MAX_CERT_BYTES = 1024
MAX_REVOKED = 65536
_SUBJECT = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
_CHUNK = re.compile(r"^(\*\*|\*|[A-Za-z0-9_.-]+)$")
_INT64_MAX = (1 << 63) - 1


class CertificateError(ValueError):
    """A certificate, revocation list or key that cannot be used; the message says why."""


def digest(encoding: bytes) -> bytes:
    """HashedId8 of an encoded structure: the last 8 bytes of SHA-256(encoding)."""
    return hashlib.sha256(encoding).digest()[-DIGEST_BYTES:]


def check_key_expr(pattern: str) -> str:
    """``pattern`` unchanged if it is a key expression of ``/``-separated chunks, each ``*``,
    ``**`` or ``[A-Za-z0-9_.-]+``; CertificateError otherwise."""
    if not isinstance(pattern, str) or not 0 < len(pattern) <= MAX_KEY_CHARS:
        raise CertificateError(f"key expression must be 1-{MAX_KEY_CHARS} characters: {pattern!r}")
    if not all(_CHUNK.fullmatch(c) for c in pattern.split("/")):
        raise CertificateError(f"invalid key expression {pattern!r}: chunks are '*', '**' or [A-Za-z0-9_.-]+")
    return pattern


def _match(pattern: list[str], key: list[str]) -> bool:
    """Chunk-wise match: ``*`` = exactly one chunk, ``**`` = zero or more chunks."""
    if not pattern:
        return not key
    head, rest = pattern[0], pattern[1:]
    if head == "**":
        return any(_match(rest, key[i:]) for i in range(len(key) + 1))
    return bool(key) and (head == "*" or head == key[0]) and _match(rest, key[1:])


def covers(patterns: tuple[str, ...], key_expr: str) -> bool:
    """True iff the concrete ``key_expr`` (no wildcards) matches one of ``patterns``."""
    chunks = key_expr.split("/")
    if any(c in ("*", "**", "") for c in chunks):
        return False
    return any(_match(p.split("/"), chunks) for p in patterns)


def default_keys(role: str, subject: str) -> tuple[str, ...]:
    """What a role publishes on by the key layout of ``schemas.keys``: an RSU its own
    ``v2x/rsu/{id}/**``, a vehicle its ``v2x/obu/{id}/**``, an operator every link's control."""
    return {"rsu": (f"v2x/rsu/{subject}/**",), "vehicle": (f"v2x/obu/{subject}/**",),
            "operator": ("v2x/link/*/control",), "ca": ()}[role]


@dataclass(frozen=True)
class Certificate:
    """A decoded certificate; ``encoding`` is the exact bytes it was decoded from (or built as)."""

    subject: str
    role: str
    keys: tuple[str, ...]
    algorithm: str
    public_key: bytes
    valid_from_ns: int
    valid_until_ns: int
    issuer: bytes
    signature: bytes
    encoding: bytes = field(repr=False, compare=False)

    @property
    def digest(self) -> bytes:
        return digest(self.encoding)

    def tbs(self) -> bytes:
        """The signed part: the msgpack encoding of the first nine fields."""
        return _pack_tbs(self.subject, self.role, self.keys, self.algorithm, self.public_key,
                         self.valid_from_ns, self.valid_until_ns, self.issuer)

    def valid_at(self, t_ns: int) -> bool:
        return self.valid_from_ns <= t_ns <= self.valid_until_ns


def _pack_tbs(subject, role, keys, algorithm, public_key, valid_from_ns, valid_until_ns, issuer) -> bytes:
    return msgpack.packb([VERSION, subject, role, list(keys), algorithm, public_key,
                          valid_from_ns, valid_until_ns, issuer])


def _check_fields(subject, role, keys, algorithm, public_key, valid_from_ns, valid_until_ns) -> None:
    if not isinstance(subject, str) or not _SUBJECT.fullmatch(subject):
        raise CertificateError(f"invalid subject {subject!r}: 1-64 characters of A-Z a-z 0-9 _ -")
    if role not in ROLES:
        raise CertificateError(f"invalid role {role!r}: expected one of {', '.join(ROLES)}")
    if not isinstance(keys, (list, tuple)) or len(keys) > MAX_KEYS:
        raise CertificateError(f"keys must be a list of at most {MAX_KEYS} key expressions")
    for k in keys:
        check_key_expr(k)
    if algorithm not in alg.ALGORITHMS:
        raise CertificateError(f"unknown algorithm {algorithm!r}")
    if not isinstance(public_key, bytes) or len(public_key) != alg.PUBLIC_KEY_BYTES[algorithm]:
        raise CertificateError(f"{algorithm} public key must be {alg.PUBLIC_KEY_BYTES[algorithm]} bytes")
    for name, t in (("valid_from_ns", valid_from_ns), ("valid_until_ns", valid_until_ns)):
        if type(t) is not int or not 0 <= t <= _INT64_MAX:
            raise CertificateError(f"{name} must be an int in [0, 2^63)")
    if valid_until_ns <= valid_from_ns:
        raise CertificateError("valid_until_ns must be after valid_from_ns")


def build(subject: str, role: str, keys: tuple[str, ...], public_key: bytes, algorithm: str,
          valid_from_ns: int, valid_until_ns: int, issuer: bytes, issuer_key: alg.PrivateKey) -> Certificate:
    """A certificate signed by ``issuer_key`` (the CA's; ``issuer`` is its digest or SELF_ISSUER)."""
    keys = tuple(keys)
    _check_fields(subject, role, keys, algorithm, public_key, valid_from_ns, valid_until_ns)
    tbs = _pack_tbs(subject, role, keys, algorithm, public_key, valid_from_ns, valid_until_ns, issuer)
    signature = alg.sign(issuer_key, tbs)
    encoding = msgpack.packb(msgpack.unpackb(tbs) + [signature])
    return Certificate(subject, role, keys, algorithm, public_key, valid_from_ns, valid_until_ns,
                       issuer, signature, encoding)


def decode(data: bytes) -> Certificate:
    """Certificate from its encoding, every field validated (the signature is not checked here:
    see :func:`verify_issued`); CertificateError on anything else."""
    if not isinstance(data, (bytes, bytearray)) or not 0 < len(data) <= MAX_CERT_BYTES:
        raise CertificateError(f"certificate must be 1-{MAX_CERT_BYTES} bytes")
    try:
        items = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True, max_array_len=MAX_KEYS + 16)
    except Exception as exc:  # msgpack raises several unrelated types on hostile bytes
        raise CertificateError(f"certificate is not msgpack: {type(exc).__name__}") from None
    if not isinstance(items, list) or len(items) != 10 or items[0] != VERSION:
        raise CertificateError(f"certificate must be a {VERSION=} array of 10 fields")
    _, subject, role, keys, algorithm, public_key, t0, t1, issuer, signature = items
    _check_fields(subject, role, keys, algorithm, public_key, t0, t1)
    if not isinstance(issuer, bytes) or len(issuer) != DIGEST_BYTES:
        raise CertificateError(f"issuer must be a {DIGEST_BYTES}-byte digest")
    if not isinstance(signature, bytes) or len(signature) != alg.SIGNATURE_BYTES:
        raise CertificateError(f"signature must be {alg.SIGNATURE_BYTES} bytes")
    cert = Certificate(subject, role, tuple(keys), algorithm, public_key, t0, t1, issuer, signature, bytes(data))
    if msgpack.packb(items) != cert.encoding:
        raise CertificateError("certificate is not in canonical msgpack form")
    return cert


def verify_issued(cert: Certificate, ca: Certificate, ca_key: alg.PublicKey) -> bool:
    """True iff ``cert`` names ``ca`` as issuer and carries ``ca``'s valid signature
    (a self-signed CA certificate: its own key over its own fields)."""
    expected_issuer = SELF_ISSUER if cert is ca or cert.encoding == ca.encoding else ca.digest
    return cert.issuer == expected_issuer and alg.verify(ca_key, cert.signature, cert.tbs())


def check_ca(ca: Certificate) -> alg.PublicKey:
    """The CA's public key after checking ``ca`` is a valid self-signed CA certificate."""
    if ca.role != "ca" or ca.issuer != SELF_ISSUER:
        raise CertificateError(f"{ca.subject!r} is not a self-signed CA certificate")
    key = alg.load_public(ca.algorithm, ca.public_key)
    if not verify_issued(ca, ca, key):
        raise CertificateError(f"CA certificate {ca.subject!r} has a bad self-signature")
    return key


@dataclass(frozen=True)
class RevocationList:
    """Digests of revoked certificates, signed by the CA at ``issued_ns``."""

    issuer: bytes
    issued_ns: int
    revoked: frozenset[bytes]
    signature: bytes

    def tbs(self) -> bytes:
        return msgpack.packb([VERSION, self.issuer, self.issued_ns, sorted(self.revoked)])

    def encode(self) -> bytes:
        return msgpack.packb([VERSION, self.issuer, self.issued_ns, sorted(self.revoked), self.signature])


def sign_revocations(revoked: frozenset[bytes], issued_ns: int, ca: Certificate,
                     ca_key: alg.PrivateKey) -> RevocationList:
    """A revocation list of ``revoked`` digests signed by the CA."""
    unsigned = RevocationList(ca.digest, issued_ns, frozenset(revoked), b"")
    return RevocationList(ca.digest, issued_ns, unsigned.revoked, alg.sign(ca_key, unsigned.tbs()))


def decode_revocations(data: bytes, ca: Certificate, ca_key: alg.PublicKey) -> RevocationList:
    """A revocation list, its fields and CA signature checked; CertificateError otherwise."""
    try:
        items = msgpack.unpackb(data, raw=False, max_array_len=MAX_REVOKED, max_bin_len=MAX_REVOKED * 16)
    except Exception as exc:
        raise CertificateError(f"revocation list is not msgpack: {type(exc).__name__}") from None
    if not isinstance(items, list) or len(items) != 5 or items[0] != VERSION:
        raise CertificateError("revocation list must be an array of 5 fields")
    _, issuer, issued_ns, revoked, signature = items
    if issuer != ca.digest:
        raise CertificateError("revocation list was not issued by this CA")
    if type(issued_ns) is not int or not isinstance(revoked, list) or not isinstance(signature, bytes):
        raise CertificateError("revocation list fields have the wrong types")
    if not all(isinstance(d, bytes) and len(d) == DIGEST_BYTES for d in revoked):
        raise CertificateError(f"revoked entries must be {DIGEST_BYTES}-byte digests")
    crl = RevocationList(issuer, issued_ns, frozenset(revoked), signature)
    if not alg.verify(ca_key, signature, crl.tbs()):
        raise CertificateError("revocation list has a bad CA signature")
    return crl
