"""security: PKI round trip, every rejection reason of the verifier, hostile envelopes."""

from __future__ import annotations

import os
import stat

import msgpack
import numpy as np
import pytest

from v2i.security import algorithms as alg
from v2i.security import certificates as certs
from v2i.security.envelope import MAGIC, PREFIX, REJECTIONS, Signer, Verifier, sign, signed_bytes
from v2i.security.pki import NS_PER_DAY, Pki, PkiError, Trust, load_signer, load_trust
from v2i.security.replay_window import ReplayWindow

T0 = 1_700_000_000 * 10**9
MS = 1_000_000
OBJ = "v2x/rsu/rsu-0/objects"
PAYLOAD = bytes(range(256)) * 12


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A site: CA, rsu-0 (P-256), rsu-1 (Ed25519), rsu-old (1 day), rsu-rev (revoked), v-0."""
    d = tmp_path_factory.mktemp("pki")
    pki = Pki.init(d, T0)
    pki.issue("rsu-0", "rsu", T0)
    pki.issue("rsu-1", "rsu", T0, algorithm=alg.ED25519)
    pki.issue("rsu-old", "rsu", T0, days=1)
    pki.issue("rsu-rev", "rsu", T0)
    pki.issue("v-0", "vehicle", T0)
    pki.revoke("rsu-rev", T0 + MS)
    return d


def signer(site, subject="rsu-0", **kw) -> Signer:
    return Signer(load_signer(site, subject), **kw)


def verifier(site, policy="strict", **kw) -> Verifier:
    return Verifier(load_trust(site), policy, **kw)


# ---------------------------------------------------------------- PKI


def test_pki_init_issue_revoke_round_trip(tmp_path):
    pki = Pki.init(tmp_path / "site", T0, ca_id="lab-ca")
    cert = pki.issue("rsu-7", "rsu", T0, days=30)
    d = tmp_path / "site"
    assert stat.S_IMODE(os.stat(d / "ca.key").st_mode) == 0o600
    assert stat.S_IMODE(os.stat(d / "rsu-7.key").st_mode) == 0o600
    assert cert.keys == ("v2x/rsu/rsu-7/**",) and cert.valid_until_ns == T0 + 30 * NS_PER_DAY
    assert cert.issuer == pki.ca.cert.digest and len(cert.digest) == 8
    trust = load_trust(d)
    assert trust.known == {cert.digest: cert.encoding} and trust.revoked == frozenset()
    assert load_signer(d, "rsu-7").cert == cert
    assert Pki.load(d).ca.cert == pki.ca.cert
    Pki.load(d).revoke("rsu-7", T0 + 5)
    assert load_trust(d).revoked == {cert.digest}
    with pytest.raises(PkiError, match="already holds a CA"):
        Pki.init(d, T0)
    with pytest.raises(PkiError, match="already has a certificate"):
        pki.issue("rsu-7", "rsu", T0)
    assert pki.issue("rsu-7", "rsu", T0, replace=True).digest != cert.digest
    with pytest.raises(PkiError, match="cannot issue role"):
        pki.issue("x", "ca", T0)


def test_certificate_encoding_round_trip_and_digest_is_last_8_bytes_of_sha256(site):
    import hashlib
    cert = load_signer(site, "rsu-1").cert
    assert certs.decode(cert.encoding) == cert and cert.algorithm == alg.ED25519
    assert cert.digest == hashlib.sha256(cert.encoding).digest()[-8:]


@pytest.mark.parametrize("damage, match", [
    (lambda d: (d / "ca.cert").unlink(), "ca.cert: missing certificate"),
    (lambda d: (d / "ca.cert").write_bytes(b"\x00garbage"), "ca.cert: corrupt certificate"),
    (lambda d: (d / "rsu-0.cert").write_bytes(b"\x95\x01"), "rsu-0.cert: corrupt certificate"),
    (lambda d: (d / "revoked.crl").write_bytes(b"\xc1"), "revoked.crl: revocation list is not msgpack"),
])
def test_load_trust_names_the_bad_file(tmp_path, damage, match):
    pki = Pki.init(tmp_path, T0)
    pki.issue("rsu-0", "rsu", T0)
    pki.revoke("rsu-0", T0)
    damage(tmp_path)
    with pytest.raises(PkiError, match=match):
        load_trust(tmp_path)


def test_tampered_revocation_list_and_ca_are_refused(tmp_path):
    pki = Pki.init(tmp_path, T0)
    pki.issue("rsu-0", "rsu", T0)
    crl = pki.revoke("rsu-0", T0)
    items = msgpack.unpackb(crl.encode())
    items[3] = []  # un-revoke without the CA key
    (tmp_path / "revoked.crl").write_bytes(msgpack.packb(items))
    with pytest.raises(PkiError, match="bad CA signature"):
        load_trust(tmp_path)
    ca = msgpack.unpackb((tmp_path / "ca.cert").read_bytes())
    ca[6] += 1
    (tmp_path / "ca.cert").write_bytes(msgpack.packb(ca))
    with pytest.raises(PkiError, match="bad self-signature"):
        load_trust(tmp_path)


def test_load_signer_refuses_open_mismatched_or_corrupt_keys(tmp_path):
    pki = Pki.init(tmp_path, T0)
    pki.issue("rsu-0", "rsu", T0)
    pki.issue("rsu-1", "rsu", T0)
    os.chmod(tmp_path / "rsu-0.key", 0o644)
    with pytest.raises(PkiError, match="accessible by others"):
        load_signer(tmp_path, "rsu-0")
    os.chmod(tmp_path / "rsu-0.key", 0o600)
    (tmp_path / "rsu-0.key").write_bytes((tmp_path / "rsu-1.key").read_bytes())
    with pytest.raises(PkiError, match="does not match certificate"):
        load_signer(tmp_path, "rsu-0")
    (tmp_path / "rsu-0.key").write_bytes(b"-----BEGIN PRIVATE KEY-----\nAAAA\n-----END PRIVATE KEY-----\n")
    with pytest.raises(PkiError, match="corrupt private key"):
        load_signer(tmp_path, "rsu-0")
    with pytest.raises(PkiError, match="missing"):
        load_signer(tmp_path, "nobody")
    with pytest.raises(PkiError, match="may not sign"):
        load_signer(tmp_path, "ca")


def test_key_coverage():
    pats = ("v2x/rsu/rsu-0/**", "v2x/link/*/control")
    assert certs.covers(pats, "v2x/rsu/rsu-0/objects") and certs.covers(pats, "v2x/rsu/rsu-0")
    assert certs.covers(pats, "v2x/link/l1/control")
    assert not certs.covers(pats, "v2x/rsu/rsu-1/objects")
    assert not certs.covers(pats, "v2x/link/l1/stats") and not certs.covers(pats, "v2x/link/a/b/control")
    assert not certs.covers(pats, "v2x/rsu/rsu-0/*"), "a wildcard key is never covered"
    with pytest.raises(certs.CertificateError):
        certs.check_key_expr("v2x/rsu/a*b")


def test_p256_raw_signature_verifies_with_the_librarys_der_form():
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.hazmat.primitives.asymmetric.utils import encode_dss_signature
    key = alg.generate(alg.P256)
    sig = alg.sign(key, b"data")
    assert len(sig) == 64 and alg.verify(key.public_key(), sig, b"data")
    der = encode_dss_signature(int.from_bytes(sig[:32], "big"), int.from_bytes(sig[32:], "big"))
    key.public_key().verify(der, b"data", ec.ECDSA(hashes.SHA256()))  # raises if not equal
    assert not alg.verify(key.public_key(), bytes(64), b"data")
    assert not alg.verify(key.public_key(), sig, b"datA")


# ---------------------------------------------------------------- verifier: accepted


@pytest.mark.parametrize("subject", ["rsu-0", "rsu-1"])
def test_genuine_messages_verify_and_certificate_travels_by_interval(site, subject):
    s, v = signer(site, subject, cert_interval_ns=500 * MS), verifier(site)
    key = f"v2x/rsu/{subject}/objects"
    envs = [sign(PAYLOAD, s, T0 + i * 100 * MS, key) for i in range(12)]
    sizes = [len(e) - len(PAYLOAD) for e in envs]
    cert_len = len(s.identity.cert.encoding)
    assert sizes[0] == sizes[5] == sizes[10] == 84 + cert_len  # full certificate, every 500 ms
    assert all(n == 92 for i, n in enumerate(sizes) if i % 5), sizes
    for i, e in enumerate(envs):
        assert v.verify(e, key, T0 + i * 100 * MS + 30 * MS) == (PAYLOAD, "ok")
    assert v.counts == {"ok": 12}


def test_certificate_checked_once_then_cached(site, monkeypatch):
    s, v = signer(site), verifier(site, cache_size=1)
    calls = []
    real = certs.verify_issued
    monkeypatch.setattr(certs, "verify_issued", lambda *a: calls.append(1) or real(*a))
    for i in range(20):
        assert v.verify(sign(PAYLOAD, s, T0 + i, OBJ), OBJ, T0)[1] == "ok"
    assert len(calls) == 1
    s1 = signer(site, "rsu-1")
    assert v.verify(sign(PAYLOAD, s1, T0, "v2x/rsu/rsu-1/objects"), "v2x/rsu/rsu-1/objects", T0)[1] == "ok"
    assert len(v._cache) == 1 and len(calls) == 2  # LRU bound: rsu-0 evicted
    assert v.verify(sign(PAYLOAD, s, T0 + 99, OBJ), OBJ, T0)[1] == "ok" and len(calls) == 3


def test_certificate_on_request_when_digest_is_unknown(site):
    trust = load_trust(site)
    v = Verifier(Trust(trust.ca, trust.ca_key, trust.revoked, {}))  # nothing pre-distributed
    s = signer(site)
    sign(PAYLOAD, s, T0, OBJ)  # first message (with certificate) lost
    lost = sign(PAYLOAD, s, T0 + 1, OBJ)
    assert v.verify(lost, OBJ, T0) == (None, "unknown_cert") and s.digest in v.wanted
    s.request_certificate()
    assert v.verify(sign(PAYLOAD, s, T0 + 2, OBJ), OBJ, T0)[1] == "ok" and s.digest not in v.wanted
    assert v.verify(sign(PAYLOAD, s, T0 + 3, OBJ), OBJ, T0)[1] == "ok"  # digest only, now cached


# ---------------------------------------------------------------- verifier: every rejection


def _resign_fields(env: bytes, **changes) -> bytes:
    items = msgpack.unpackb(env)
    for index, value in changes.items():
        items[int(index[1:])] = value
    return msgpack.packb(items)


def test_every_rejection_reason_is_triggered_and_counted(site, tmp_path):
    s, v = signer(site), verifier(site, freshness_ns=1000 * MS, future_ns=100 * MS, roles=("rsu",))
    good = sign(PAYLOAD, s, T0, OBJ)
    sig = msgpack.unpackb(good)[4]
    other = Pki.init(tmp_path, T0)
    other.issue("rsu-0", "rsu", T0)  # same name, other CA
    expected = {
        "unsigned": [PAYLOAD, b""],
        "malformed": [PREFIX + b"\x00", good[:-1], _resign_fields(good, f3="now")],
        "bad_signature": [_resign_fields(good, f1=PAYLOAD[:-1] + b"X"),
                          _resign_fields(good, f4=bytes([sig[0] ^ 1]) + sig[1:]),
                          _resign_fields(good, f3=T0 + 1)],
        "unknown_cert": [sign(PAYLOAD, Signer(load_signer(tmp_path, "rsu-0")), T0, OBJ),
                         _resign_fields(sign(PAYLOAD, s, T0 + 5, OBJ), f2=bytes(8))],
        "revoked": [sign(PAYLOAD, signer(site, "rsu-rev"), T0, "v2x/rsu/rsu-rev/objects")],
        "expired": [sign(PAYLOAD, signer(site, "rsu-old"), T0 + 2 * NS_PER_DAY, "v2x/rsu/rsu-old/objects"),
                    sign(PAYLOAD, s, T0 - 1, OBJ)],
        "wrong_role": [sign(PAYLOAD, signer(site, "v-0"), T0, OBJ)],  # this receiver takes RSUs only
        "wrong_key": [sign(PAYLOAD, signer(site, "rsu-1"), T0, OBJ)],  # another RSU on rsu-0's key
        "stale": [sign(PAYLOAD, s, T0 + 10, OBJ)],
        "future": [sign(PAYLOAD, s, T0 + 10**9, OBJ)],
        "replayed": [good],
    }
    now = {"stale": T0 + 2000 * MS, "expired": T0 + 2 * NS_PER_DAY}
    assert v.verify(good, OBJ, T0) == (PAYLOAD, "ok")
    for reason, envs in expected.items():
        for e in envs:
            key = "v2x/rsu/rsu-rev/objects" if reason == "revoked" else OBJ
            key = "v2x/rsu/rsu-old/objects" if e is envs[0] and reason == "expired" else key
            assert v.verify(e, key, now.get(reason, T0)) == (None, reason), reason
    assert v.rejected() == {r: len(expected[r]) for r in REJECTIONS}
    assert v.counts["ok"] == 1


def test_forged_certificate_widening_its_keys_is_a_bad_signature(site):
    s, v = signer(site, "v-0"), verifier(site)
    items = msgpack.unpackb(s.identity.cert.encoding)
    items[3] = ["**"]  # the vehicle grants itself every key
    forged = msgpack.packb(items)
    tbs = signed_bytes(PAYLOAD, certs.digest(forged), T0, OBJ)
    env = msgpack.packb([MAGIC, PAYLOAD, forged, T0, alg.sign(s.identity.key, tbs)])
    assert v.verify(env, OBJ, T0) == (None, "bad_signature")


def test_key_substitution_is_a_bad_signature(site):
    """A genuine objects list re-published on the RSU's predictions key (both covered)."""
    s, v = signer(site), verifier(site)
    env = sign(PAYLOAD, s, T0, OBJ)
    assert v.verify(env, "v2x/rsu/rsu-0/predictions", T0) == (None, "bad_signature")
    assert v.verify(env, OBJ, T0) == (PAYLOAD, "ok")


def test_revocation_reloaded_at_run_time_applies_to_a_cached_certificate(tmp_path):
    pki = Pki.init(tmp_path, T0)
    pki.issue("rsu-0", "rsu", T0)
    s, v = signer(tmp_path), verifier(tmp_path)
    assert v.verify(sign(PAYLOAD, s, T0, OBJ), OBJ, T0)[1] == "ok"
    pki.revoke("rsu-0", T0 + 1)
    assert v.verify(sign(PAYLOAD, s, T0 + 1, OBJ), OBJ, T0)[1] == "ok", "old trust until reloaded"
    v.set_trust(load_trust(tmp_path))
    assert v.verify(sign(PAYLOAD, s, T0 + 2, OBJ), OBJ, T0) == (None, "revoked")
    other = Pki.init(tmp_path / "other", T0)
    other.issue("rsu-0", "rsu", T0)
    v.set_trust(load_trust(tmp_path / "other"))
    assert v.verify(sign(PAYLOAD, s, T0 + 3, OBJ), OBJ, T0) == (None, "unknown_cert"), "old CA's cache dropped"


def test_replay_is_remembered_for_the_window_then_stale(site):
    s = signer(site)
    v = verifier(site, freshness_ns=1000 * MS, replay_window_ns=1000 * MS)
    first = sign(PAYLOAD, s, T0, OBJ)
    assert v.verify(first, OBJ, T0)[1] == "ok"
    assert v.verify(first, OBJ, T0 + 500 * MS)[1] == "replayed"
    assert v.verify(sign(PAYLOAD, s, T0 + 1500 * MS, OBJ), OBJ, T0 + 1500 * MS)[1] == "ok"
    assert v.verify(first, OBJ, None)[1] == "stale", "no freshness check, but beyond the replay window"
    with pytest.raises(ValueError):
        Verifier(load_trust(site), freshness_ns=10, replay_window_ns=5)


def test_replay_window_memory_is_bounded():
    w = ReplayWindow(window_ns=10**12, per_signer=100, max_signers=3)
    for t in range(1000):
        assert w.check_and_add(b"a" * 8, t, b"h") == "ok"
    assert len(w) == 100
    assert w.check_and_add(b"a" * 8, 899, b"h") == "stale", "evicted for capacity: cannot be proven new"
    assert w.check_and_add(b"a" * 8, 950, b"h") == "replayed"
    assert w.check_and_add(b"a" * 8, 950, b"other payload") == "ok"
    for i in range(10):
        w.check_and_add(bytes([i]) * 8, 1, b"h")
    assert len(w._signers) == 3


@pytest.mark.parametrize("policy", ["strict", "permissive", "off"])
def test_policies_on_unsigned_forged_and_genuine(site, policy):
    s, v = signer(site), verifier(site, policy)
    good = sign(PAYLOAD, s, T0, OBJ)
    forged = _resign_fields(good, f1=b"ghost pedestrian")
    unsigned_out = v.verify(PAYLOAD, OBJ, T0)
    forged_out = v.verify(forged, OBJ, T0)
    assert v.verify(good, OBJ, T0)[0] == PAYLOAD
    if policy == "strict":
        assert (unsigned_out, forged_out) == ((None, "unsigned"), (None, "bad_signature"))
    elif policy == "permissive":
        assert (unsigned_out, forged_out) == ((PAYLOAD, "unsigned"), (b"ghost pedestrian", "bad_signature"))
    else:
        assert (unsigned_out, forged_out) == ((PAYLOAD, "unchecked"), (b"ghost pedestrian", "unchecked"))
        assert v.rejected() == dict.fromkeys(REJECTIONS, 0)
    assert sum(v.counts.values()) == 3
    with pytest.raises(ValueError, match="unknown security policy"):
        Verifier(load_trust(site), "lenient")


# ---------------------------------------------------------------- hostile bytes


def _hostile(good: bytes, rng: np.random.Generator):
    yield from (good[:n] for n in range(len(good)))
    yield from (PREFIX + rng.bytes(int(n)) for n in rng.integers(0, 300, 200))
    yield from (rng.bytes(int(n)) for n in rng.integers(0, 300, 200))
    for _ in range(300):
        flipped = bytearray(good)
        flipped[int(rng.integers(len(good)))] ^= 1 << int(rng.integers(8))
        yield bytes(flipped)
    yield PREFIX + b"\xc6\xff\xff\xff\xff"  # payload bin32 declaring 4 GiB
    yield PREFIX + b"\xc5\xff\xff" + bytes(10)  # bin16 declaring 64 KiB, truncated
    yield b"\x95\xcd\x56\x01" + b"\xdd\xff\xff\xff\xff"  # array32 of 2^32 - 1 items
    yield PREFIX + b"\xc4\x01x\xc4\x08" + bytes(8) + b"\xcf" + b"\xff" * 8 + b"\xc4\x40" + bytes(64)
    yield PREFIX + b"\xc4\x01x\xc4\x08" + bytes(8) + b"\xd3" + b"\xff" * 8 + b"\xc4\x40" + bytes(64)  # int64 -1
    yield PREFIX + bytes(2 << 20)  # over the size bound
    yield msgpack.packb([MAGIC, b"p", b"s" * 2000, T0, bytes(64)])  # signer too long
    yield msgpack.packb([MAGIC, b"p", b"s" * 300, T0, bytes(64)])  # a "certificate" of junk
    yield msgpack.packb([MAGIC, [1, 2], bytes(8), T0, bytes(64)])
    yield msgpack.packb([MAGIC, b"p", bytes(8), T0, bytes(64), b"extra"])


@pytest.mark.parametrize("policy", ["strict", "permissive", "off"])
def test_hostile_envelopes_are_counted_rejections_never_exceptions(site, policy):
    rng = np.random.default_rng(14)
    s, v = signer(site), verifier(site, policy)
    good = sign(PAYLOAD[:40], s, T0, OBJ)
    n = 0
    for data in _hostile(good, rng):
        payload, reason = v.verify(data, OBJ, T0)
        n += 1
        assert reason in REJECTIONS + ("ok", "unchecked")
        if policy == "strict":
            assert (payload is None) == (reason != "ok")
    assert sum(v.counts.values()) == n
    if policy == "strict":
        assert v.counts["ok"] <= 1 and v.counts["malformed"] > 200 and v.counts["unsigned"] >= 200
