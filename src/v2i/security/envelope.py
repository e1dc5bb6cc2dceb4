"""Signed envelopes around V2X payloads, and their verifier (IEEE 1609.2 ``SignedData`` in spirit).

Wire form, one msgpack array (the payload bytes are carried unchanged):

    [MAGIC, payload, signer, generation_ns, signature]

- ``MAGIC`` = 0x5601 ("V", envelope version 1), so every envelope starts with the four bytes
  ``95 cd 56 01``; v2i's own messages start with ``94`` (object lists) or ``8x`` (maps), so
  anything else is *unsigned*, and anything with the prefix that does not parse is *malformed*.
- ``signer``: 8 bytes = the certificate's digest (1609.2 ``HashedId8``), or the whole
  certificate encoding (~170 B; 1609.2 ``SignerIdentifier.certificate``).
- ``signature``: 64 B (P-256 raw ``r || s`` or Ed25519) over
  ``DOMAIN || digest || generation_ns (8 B big-endian) || key_expr || 0x00 || payload``.
  The key expression is signed too (as 1609.2 signs the PSID), so a genuine message cannot be
  moved to another key its certificate also covers (e.g. ``objects`` -> ``predictions``).

Bytes added with a digest signer and a payload under 64 KiB: 1 (array) + 3 (magic) + 3 (bin16
header) + 2 + 8 (digest) + 9 (uint64 time) + 2 + 64 (signature) = **92 B**; 2 more for payloads
of 64 KiB or more. A message carrying its full certificate adds the certificate's size instead
of the 8-byte digest.

Certificate distribution (1609.2's rule for BSMs, by time): a :class:`Signer` puts its full
certificate in its first message, then in one message per ``cert_interval_ns`` of generation
time (default 1 s), and in the next message after :meth:`Signer.request_certificate` (wired to a
peer's request for an unknown digest); every other message carries the digest. A verifier also
knows the certificates of its trust directory in advance. A certificate is checked against the
CA once (signature, issuer, role) and then cached by digest (bounded LRU); validity time, key
coverage and revocation are checked per message against the cached entry (a set lookup and two
comparisons). Digests the verifier could not resolve are kept (bounded) in
:attr:`Verifier.wanted` so the wiring can ask the signer for its certificate.

Policies: ``strict`` drops every failure; ``permissive`` counts the failure and still returns the
payload when one can be extracted (not for ``malformed``); ``off`` unwraps envelopes without any
check (reason ``unchecked``) and passes unsigned bytes through. Every call counts its reason.

Checks, cheapest first (a forged message costs no signature verification unless it names a
valid, unrevoked, in-date certificate that covers the key): parse -> signer certificate
(cache, else CA check) -> revoked -> expired (generation time outside the certificate's
validity) -> wrong_role (not one of the verifier's ``roles``, e.g. only operators may control a
link) -> wrong_key -> stale / future (against ``now_ns``) -> signature -> replay window.
``now_ns`` must be in the signer's clock (the OBU passes its own time plus its estimated offset
to that RSU), or ``None`` to skip the freshness check (e.g. before clock sync, for time replies,
which the OBU binds to its request by the echoed t1 instead).
"""

from __future__ import annotations

import hashlib
from collections import Counter, OrderedDict
from dataclasses import dataclass

import msgpack

from v2i.security import algorithms as alg
from v2i.security import certificates as certs
from v2i.security.certificates import Certificate, CertificateError
from v2i.security.pki import Identity, Trust
from v2i.security.replay_window import ReplayWindow

MAGIC = 0x5601
PREFIX = bytes([0x95, 0xCD, 0x56, 0x01])
DOMAIN = b"v2i-signed-v1\x00"
MAX_ENVELOPE_BYTES = (1 << 20) + 2048
POLICIES = ("strict", "permissive", "off")
REJECTIONS = ("unsigned", "malformed", "bad_signature", "unknown_cert", "revoked", "expired", "wrong_role",
              "wrong_key", "stale", "future", "replayed")
_UINT64_MAX = (1 << 64) - 1
_WANTED_MAX = 64


def signed_bytes(payload: bytes, digest: bytes, generation_ns: int, key_expr: str) -> bytes:
    """The bytes the signature covers (see the module docstring)."""
    return b"".join((DOMAIN, digest, generation_ns.to_bytes(8, "big"), key_expr.encode(), b"\x00", payload))


class Signer:
    """Signs payloads as ``identity``; decides when the full certificate travels."""

    def __init__(self, identity: Identity, cert_interval_ns: int = 1_000_000_000) -> None:
        self.identity = identity
        self.digest = identity.cert.digest
        self.cert_interval_ns = cert_interval_ns
        self._last_cert_ns: int | None = None
        self._cert_requested = False

    def request_certificate(self) -> None:
        """Carry the full certificate in the next message (a peer asked for it)."""
        self._cert_requested = True

    def _signer_field(self, generation_ns: int) -> bytes:
        last = self._last_cert_ns
        if self._cert_requested or last is None or not 0 <= generation_ns - last < self.cert_interval_ns:
            self._last_cert_ns, self._cert_requested = generation_ns, False
            return self.identity.cert.encoding
        return self.digest

    def sign(self, payload: bytes, generation_ns: int, key_expr: str) -> bytes:
        signature = alg.sign(self.identity.key, signed_bytes(payload, self.digest, generation_ns, key_expr))
        return msgpack.packb([MAGIC, payload, self._signer_field(generation_ns), generation_ns, signature])


def sign(payload: bytes, signer: Signer | None, generation_ns: int, key_expr: str) -> bytes:
    """``payload`` wrapped in an envelope signed by ``signer`` at ``generation_ns`` for ``key_expr``;
    unchanged without a signer (a node started without ``--pki``)."""
    return payload if signer is None else signer.sign(payload, generation_ns, key_expr)


@dataclass(frozen=True)
class _Parsed:
    payload: bytes
    signer: bytes
    generation_ns: int
    signature: bytes


def parse(data: bytes) -> _Parsed | None:
    """The fields of an envelope (types and sizes checked), or None if it is malformed."""
    if len(data) > MAX_ENVELOPE_BYTES:
        return None
    try:
        items = msgpack.unpackb(data, raw=True, max_array_len=5, max_map_len=0, max_str_len=0,
                                max_ext_len=0, max_bin_len=MAX_ENVELOPE_BYTES)
    except Exception:  # msgpack raises several unrelated types on hostile bytes
        return None
    if not isinstance(items, list) or len(items) != 5 or items[0] != MAGIC:
        return None
    _, payload, signer, generation_ns, signature = items
    if not (isinstance(payload, bytes) and isinstance(signer, bytes) and isinstance(signature, bytes)):
        return None
    if type(generation_ns) is not int or not 0 <= generation_ns <= _UINT64_MAX:
        return None
    if len(signature) != alg.SIGNATURE_BYTES or not certs.DIGEST_BYTES <= len(signer) <= certs.MAX_CERT_BYTES:
        return None
    return _Parsed(payload, signer, generation_ns, signature)


def unwrap(data: bytes) -> bytes:
    """The payload of an envelope, else ``data`` unchanged (unsigned or malformed bytes); no check
    at all and never raises: for readers of recorded or mirrored traffic, not for trust decisions."""
    data = bytes(data)
    if not data.startswith(PREFIX):
        return data
    env = parse(data)
    return data if env is None else env.payload


@dataclass(frozen=True)
class _Entry:
    cert: Certificate
    key: alg.PublicKey


class Verifier:
    """Verifies envelopes against ``trust`` under ``policy``; counts every outcome by reason
    (``trust`` may be None only under ``off``, which unwraps without checking).

    ``freshness_ns``: the oldest accepted age ``now_ns - generation_ns``; ``future_ns``: how far
    ahead of ``now_ns`` a generation time may be; ``replay_window_ns`` (>= ``freshness_ns``): how
    long seen messages are remembered, per signer and key expression (each a stream of its own: a
    receiver may handle one key's backlog after newer messages of another, and a replay on another
    key fails its signature), in the signer's clock; ``roles``: the certificate roles this receiver
    accepts at all. Not thread-safe: one owner (the service loop) calls it.
    """

    def __init__(self, trust: Trust | None, policy: str = "strict", freshness_ns: int = 2_000_000_000,
                 future_ns: int = 200_000_000, replay_window_ns: int | None = None,
                 cache_size: int = 256, roles: tuple[str, ...] = certs.SIGNER_ROLES) -> None:
        if policy not in POLICIES:
            raise ValueError(f"unknown security policy {policy!r}: expected one of {', '.join(POLICIES)}")
        if trust is None and policy != "off":
            raise ValueError(f"security policy {policy!r} needs a trust (a site CA); only 'off' checks nothing")
        window_ns = freshness_ns if replay_window_ns is None else replay_window_ns
        if window_ns < freshness_ns:
            raise ValueError("replay_window_ns must be >= freshness_ns, or a replay could be fresh but forgotten")
        self.trust, self.policy, self.roles = trust, policy, roles
        self.freshness_ns, self.future_ns = freshness_ns, future_ns
        self.replay = ReplayWindow(window_ns)
        self.cache_size = cache_size
        self._cache: OrderedDict[bytes, _Entry] = OrderedDict()
        self.counts: Counter[str] = Counter()
        self.wanted: OrderedDict[bytes, None] = OrderedDict()
        self.last_signer: bytes | None = None  # the last verified message's certificate digest (verify)

    def set_trust(self, trust: Trust) -> None:
        """Take a reloaded trust directory (e.g. a new revocation list); revocation applies to
        cached certificates at once, and the cache is emptied if the CA changed."""
        if self.trust is None or trust.ca.encoding != self.trust.ca.encoding:
            self._cache.clear()
        self.trust = trust

    def _cached(self, digest: bytes) -> _Entry | None:
        entry = self._cache.get(digest)
        if entry is not None:
            self._cache.move_to_end(digest)
        return entry

    def _admit(self, encoding: bytes, digest: bytes) -> _Entry | str:
        """CA-check a certificate once and cache it, or the rejection reason."""
        try:
            cert = certs.decode(encoding)
        except CertificateError:
            return "malformed"
        if cert.issuer != self.trust.ca.digest or cert.role not in certs.SIGNER_ROLES:
            return "unknown_cert"
        if not certs.verify_issued(cert, self.trust.ca, self.trust.ca_key):
            return "bad_signature"
        try:
            entry = _Entry(cert, alg.load_public(cert.algorithm, cert.public_key))
        except ValueError:
            return "malformed"
        self._cache[digest] = entry
        if len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return entry

    def _resolve(self, signer: bytes) -> tuple[bytes, _Entry | str]:
        """(digest, cached entry or rejection reason) of an envelope's signer field."""
        digest = signer if len(signer) == certs.DIGEST_BYTES else certs.digest(signer)
        entry = self._cached(digest)
        if entry is not None:
            return digest, entry
        encoding = signer if len(signer) != certs.DIGEST_BYTES else self.trust.known.get(digest)
        if encoding is None:
            self.wanted[digest] = None
            if len(self.wanted) > _WANTED_MAX:
                self.wanted.popitem(last=False)
            return digest, "unknown_cert"
        self.wanted.pop(digest, None)
        return digest, self._admit(encoding, digest)

    def _check_time(self, generation_ns: int, now_ns: int | None) -> str | None:
        if now_ns is None:
            return None
        if now_ns - generation_ns > self.freshness_ns:
            return "stale"
        if generation_ns - now_ns > self.future_ns:
            return "future"
        return None

    def _check(self, env: _Parsed, key_expr: str, now_ns: int | None) -> str:
        """``"ok"`` or the first rejection reason, cheapest checks first."""
        digest, entry = self._resolve(env.signer)
        if isinstance(entry, str):
            return entry
        self.last_signer, cert = digest, entry.cert
        if digest in self.trust.revoked:
            return "revoked"
        if not cert.valid_at(env.generation_ns):
            return "expired"
        if cert.role not in self.roles:
            return "wrong_role"
        if not certs.covers(cert.keys, key_expr):
            return "wrong_key"
        late = self._check_time(env.generation_ns, now_ns)
        if late:
            return late
        if not alg.verify(entry.key, env.signature, signed_bytes(env.payload, digest, env.generation_ns, key_expr)):
            return "bad_signature"
        stream = digest + key_expr.encode()  # one window per signer and key (class docstring)
        return self.replay.check_and_add(stream, env.generation_ns, hashlib.sha256(env.payload).digest()[:16])

    def _outcome(self, payload: bytes | None, reason: str) -> tuple[bytes | None, str]:
        self.counts[reason] += 1
        if reason in ("ok", "unchecked") or self.policy == "permissive":
            return payload, reason
        return None, reason

    def verify(self, data: bytes, key_expr: str, now_ns: int | None) -> tuple[bytes | None, str]:
        """(payload or None, reason) for the bytes received on ``key_expr`` at ``now_ns`` (signer's
        clock, or None: no freshness check). ``reason`` is ``ok``, ``unchecked`` (policy off) or
        one of :data:`REJECTIONS`; never raises on any input bytes. ``last_signer``: the digest of
        the certificate that signed it, once the envelope named one the verifier knows (else None)."""
        data = bytes(data)
        self.last_signer = None
        if not data.startswith(PREFIX):
            return self._outcome(data, "unchecked" if self.policy == "off" else "unsigned")
        env = parse(data)
        if env is None:
            off = self.policy == "off"
            return self._outcome(data if off else None, "unchecked" if off else "malformed")
        if self.policy == "off":
            return self._outcome(env.payload, "unchecked")
        return self._outcome(env.payload, self._check(env, key_expr, now_ns))

    def rejected(self) -> dict[str, int]:
        """Counts of every rejection reason (zeros included), for metrics."""
        return {reason: self.counts[reason] for reason in REJECTIONS}
