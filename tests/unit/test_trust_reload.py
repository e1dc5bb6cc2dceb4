"""v2i.security.trust_reload and the OBU's use of it: a revocation list written while a verifier runs is
taken within the poll interval; a bad, foreign, older or removed list is refused and the list in force kept."""

from __future__ import annotations

from collections import Counter
from types import SimpleNamespace

import msgpack
import pytest

from obu_service.inbound_security import live_security
from v2i.security.envelope import Signer, Verifier
from v2i.security.pki import CRL_FILE, Pki, load_signer
from v2i.security.site import write_site
from v2i.security.trust_reload import TrustReload

T0 = 1_800_000_000 * 10**9
S = 1_000_000_000
KEY = "v2x/rsu/rsu1/objects"


@pytest.fixture
def site(tmp_path):
    return write_site(tmp_path / "pki", T0 - 86_400 * S, ["rsu1", "rsu2", "rsu3"], ["ego"])


def _check(verifier: Verifier, site, subject: str, t_ns: int) -> str:
    key = f"v2x/rsu/{subject}/objects"
    return verifier.verify(Signer(load_signer(site, subject)).sign(b"list", t_ns, key), key, t_ns)[1]


def _follow(reload: TrustReload, verifier: Verifier, now_ns: int):
    """One poll, its accepted trust handed to the verifier as the services do; the outcome."""
    outcome = reload.poll(now_ns)
    if outcome is not None and outcome.accepted:
        verifier.set_trust(outcome.trust)
    return outcome


def test_a_revocation_is_taken_at_the_next_poll_a_second_on_and_applies_to_a_cached_certificate(site):
    reload = TrustReload(site)
    verifier = Verifier(reload.trust, "strict")
    assert _follow(reload, verifier, T0) is None  # nothing changed since the load
    assert _check(verifier, site, "rsu1", T0) == "ok"  # rsu1's certificate now cached
    Pki.load(site).revoke("rsu1", T0)
    assert _follow(reload, verifier, T0 + S - 1) is None  # within the interval: not even looked at
    assert _check(verifier, site, "rsu1", T0 + 1) == "ok"
    outcome = _follow(reload, verifier, T0 + S)
    assert outcome.accepted and outcome.revoked == 1 and "1 certificate(s) revoked" in outcome.describe()
    assert _check(verifier, site, "rsu1", T0 + 2) == "revoked"
    assert _check(verifier, site, "rsu2", T0 + 2) == "ok"
    assert _follow(reload, verifier, T0 + 5 * S) is None  # the same file: nothing to do


@pytest.mark.parametrize("damage, why", [
    (lambda site, crl: b"\xc1not msgpack", "not msgpack"),
    (lambda site, crl: _unrevoked(crl), "bad CA signature"),  # the CA's list with an entry taken out
    (lambda site, crl: _foreign(site), "not issued by this CA"),  # another CA's list
])
def test_a_list_that_does_not_verify_is_refused_once_and_the_list_in_force_kept(site, damage, why):
    pki = Pki.load(site)
    pki.revoke("rsu1", T0)
    reload = TrustReload(site)
    verifier = Verifier(reload.trust, "strict")
    good = (site / CRL_FILE).read_bytes()
    (site / CRL_FILE).write_bytes(damage(site, good))
    outcome = _follow(reload, verifier, T0)
    assert not outcome.accepted and why in outcome.reason and outcome.revoked == 1
    assert "refused" in outcome.describe() and "kept the previous list" in outcome.describe()
    assert _check(verifier, site, "rsu1", T0) == "revoked" and _check(verifier, site, "rsu2", T0) == "ok"
    assert _follow(reload, verifier, T0 + S) is None  # refused once per change, not once a second
    (site / CRL_FILE).write_bytes(good)  # the CA puts its list back and revokes one more: taken
    pki.revoke("rsu2", T0 + S)
    assert _follow(reload, verifier, T0 + 2 * S).accepted
    assert _check(verifier, site, "rsu2", T0 + 2 * S) == "revoked" and _check(verifier, site, "rsu3", T0) == "ok"


def _unrevoked(crl: bytes) -> bytes:
    items = msgpack.unpackb(crl)
    items[3] = []
    return msgpack.packb(items)


def _foreign(site) -> bytes:
    other = site.parent / "other"
    write_site(other, T0, ["rsu9"])
    Pki.load(other).revoke("rsu9", T0)
    return (other / CRL_FILE).read_bytes()


def test_an_older_list_put_back_or_a_removed_list_is_refused(site):
    pki = Pki.load(site)
    pki.revoke("rsu1", T0)
    older = (site / CRL_FILE).read_bytes()
    pki.revoke("rsu2", T0 + S)
    reload = TrustReload(site)
    verifier = Verifier(reload.trust, "strict")
    (site / CRL_FILE).write_bytes(older)  # genuinely the CA's, but it would un-revoke rsu2
    outcome = _follow(reload, verifier, T0)
    assert not outcome.accepted and "leaves out 1 certificate(s)" in outcome.reason
    (site / CRL_FILE).unlink()
    outcome = _follow(reload, verifier, T0 + S)
    assert not outcome.accepted and "removed" in outcome.reason
    assert {_check(verifier, site, s, T0 + S) for s in ("rsu1", "rsu2")} == {"revoked"}
    pki.revoke("rsu3", T0 + 3 * S)  # the CA, its list lost, starts a new one: refused as well
    assert "leaves out 2 certificate(s)" in _follow(reload, verifier, T0 + 2 * S).reason
    pki.revoke("rsu1", T0 + 4 * S)
    pki.revoke("rsu2", T0 + 4 * S)  # all three: taken
    assert _follow(reload, verifier, T0 + 3 * S).accepted and len(verifier.trust.revoked) == 3


def test_without_a_list_at_start_the_first_one_written_is_taken(site):
    reload = TrustReload(site)
    assert reload.trust.revoked == frozenset()
    Pki.load(site).revoke("rsu3", T0)
    outcome = reload.poll(T0)
    assert outcome.accepted and outcome.trust.revoked == {load_signer(site, "rsu3").cert.digest}
    assert outcome.trust.known == reload.trust.known and outcome.trust.ca == reload.trust.ca


def _live(site, policy: str):
    counts: Counter = Counter()
    gate = live_security(str(site), policy, 5.0, lambda rsu_id, t_ns: SimpleNamespace(offset_ns=0),
                         lambda label: counts.update([label]))
    return gate, counts


def test_the_obu_gate_takes_a_revocation_between_messages_and_drops_the_revoked_rsu_by_reason(site):
    gate, counts = _live(site, "strict")
    rsu1 = Signer(load_signer(site, "rsu1"))
    assert gate.open(rsu1.sign(b"a", T0, KEY), KEY, T0) == b"a"
    Pki.load(site).revoke("rsu1", T0)
    assert gate.open(rsu1.sign(b"b", T0 + 1, KEY), KEY, T0 + 1) == b"b"  # messages alone do not reload
    line = gate.poll_trust(T0 + 2)
    assert line.startswith("reloaded ") and str(site / CRL_FILE) in line
    assert gate.open(rsu1.sign(b"c", T0 + 3, KEY), KEY, T0 + 3) is None
    assert counts == Counter({"security_revoked": 1})
    assert gate.poll_trust(T0 + 3) is None


def test_an_obu_that_checks_nothing_does_not_watch_the_list(site):
    gate, _ = _live(site, "off")
    Pki.load(site).revoke("rsu1", T0)
    assert gate.poll_trust(T0) is None
    gate, _ = _live(site, "permissive")
    Pki.load(site).revoke("rsu2", T0 + S)
    assert gate.poll_trust(T0 + S).startswith("reloaded ")
    with pytest.raises(ValueError, match="ca.cert"):
        live_security(str(site / "absent"), "strict", 5.0, lambda rsu_id, t_ns: None, lambda label: None)
