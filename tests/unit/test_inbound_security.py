"""obu_service.inbound_security: what the OBU lets through from signed RSU messages."""

from collections import Counter
from types import SimpleNamespace

from obu_service.inbound_security import InboundSecurity, envelope_screen, make_verifier
from v2i.security.envelope import Signer
from v2i.security.site import memory_site

NOW_NS = 1_800_000_000 * 10**9
OFFSET_NS = 3 * 10**9  # the RSU's clock runs 3 s ahead of the OBU's
KEY = "v2x/rsu/rsu1/objects"
TRUST, IDS = memory_site(NOW_NS - 86_400 * 10**9, ["rsu1", "rsu2"], ["ego"])  # valid from a day before


def _gate(policy: str = "strict", estimated: bool = True) -> tuple[InboundSecurity, Counter]:
    counts: Counter = Counter()
    offset = (lambda rsu_id, t_ns: SimpleNamespace(offset_ns=OFFSET_NS)) if estimated else (lambda rsu_id, t_ns: None)
    gate = InboundSecurity(make_verifier(TRUST if policy != "off" else None, policy, 5.0), offset,
                           lambda label: counts.update([label]))
    return gate, counts


def _signed(payload: bytes, rsu_age_s: float, key: str = KEY, who: str = "rsu1") -> bytes:
    """Signed by ``who`` with a generation time ``rsu_age_s`` before the OBU's receive time, in the RSU's clock."""
    return Signer(IDS[who]).sign(payload, NOW_NS + OFFSET_NS - round(rsu_age_s * 1e9), key)


def test_freshness_is_judged_in_the_rsu_clock_through_the_offset_estimate():
    gate, counts = _gate()
    assert gate.open(_signed(b"fresh", 0.05), KEY, NOW_NS) == b"fresh"  # 3 s "ahead" of the OBU, 50 ms old
    assert gate.open(_signed(b"old", 6.0), KEY, NOW_NS) is None
    assert gate.open(_signed(b"ahead", -2.0), KEY, NOW_NS) is None
    assert counts == Counter({"security_stale": 1, "security_future": 1})


def test_before_the_clock_is_estimated_only_the_replay_window_applies():
    gate, counts = _gate(estimated=False)
    data = _signed(b"x", 6.0)
    assert gate.open(data, KEY, NOW_NS) == b"x"
    assert gate.open(data, KEY, NOW_NS) is None
    assert counts == Counter({"security_replayed": 1})


def test_time_replies_skip_freshness_but_not_the_signature():
    gate, counts = _gate()
    key = "v2x/rsu/rsu1/time"
    assert gate.open(_signed(b"reply", 30.0, key), key, NOW_NS, time_reply=True) == b"reply"
    assert gate.open(_signed(b"forged", 0.0, key, who="rsu2"), key, NOW_NS, time_reply=True) is None
    assert gate.open(b"\x85unsigned", key, NOW_NS, time_reply=True) is None
    assert counts == Counter({"security_wrong_key": 1, "security_unsigned": 1})  # another RSU on rsu1's key


def test_permissive_counts_under_its_own_label_and_lets_through():
    gate, counts = _gate("permissive")
    assert gate.open(b"\x94plain", KEY, NOW_NS) == b"\x94plain"
    assert gate.open(_signed(b"ghost", 0.0, who="ego"), KEY, NOW_NS) == b"ghost"
    assert counts == Counter({"security_accepted_unsigned": 1, "security_accepted_wrong_role": 1})  # a vehicle's


def test_off_unwraps_without_counting():
    gate, counts = _gate("off")
    assert gate.open(_signed(b"list", 100.0, who="ego"), KEY, NOW_NS) == b"list"
    assert gate.open(b"\x94plain", KEY, NOW_NS) == b"\x94plain"
    assert not counts


def test_policy_off_asks_no_clock_estimate_and_passes_what_it_gets():
    asked = []
    gate = InboundSecurity(make_verifier(None, "off", 5.0), lambda rsu_id, t_ns: asked.append(rsu_id),
                           lambda label: None)
    assert gate.open(b"\x94plain", KEY, NOW_NS) == b"\x94plain"
    assert gate.open(_signed(b"wrapped", 0.05), KEY, NOW_NS) == b"wrapped"  # unwrapped unchecked
    assert asked == [] and gate.verifier.counts["unchecked"] == 2
    checked = []
    strict = InboundSecurity(make_verifier(TRUST, "strict", 5.0), lambda rsu_id, t_ns: checked.append(rsu_id),
                             lambda label: None)
    strict.open(_signed(b"fresh", 0.05), KEY, NOW_NS)
    assert checked == ["rsu1"]  # a checking policy still asks


def test_each_verified_signer_has_its_own_budget_that_forgeries_naming_it_cannot_spend():
    counts: Counter = Counter()
    gate = InboundSecurity(make_verifier(TRUST, "strict", 5.0), lambda rsu_id, t_ns: SimpleNamespace(offset_ns=OFFSET_NS),
                           lambda label: counts.update([label]), signer_rate_hz=10.0, signer_burst=3)
    genuine = [_signed(b"g%d" % k, 0.01 * k) for k in range(4)]
    forged = bytearray(genuine[0])
    forged[-1] ^= 0xFF  # the genuine signer named, the signature broken
    for k in range(100):  # a flood naming rsu1 costs one verify each and never takes rsu1's tokens
        assert gate.open(bytes(forged[:-8]) + bytes([k]) * 8, KEY, NOW_NS) is None
    assert [gate.open(g, KEY, NOW_NS) for g in genuine[:3]] == [b"g0", b"g1", b"g2"]  # the burst, all genuine
    assert gate.open(genuine[3], KEY, NOW_NS) is None  # rsu1 itself over its own budget
    other = "v2x/rsu/rsu2/objects"
    assert gate.open(_signed(b"r2", 0.0, other, who="rsu2"), other, NOW_NS) == b"r2"  # another signer's is its own
    assert counts == Counter({"security_bad_signature": 100, "signer_rate_limited": 1})
    assert gate.open(genuine[3], KEY, NOW_NS + 10**8) is None  # replayed now (it was verified once)


def test_a_site_whose_messages_never_verify_is_warned_about_once_until_one_does():
    gate, counts = _gate()
    t = NOW_NS
    for k in range(11):  # every second for 10 s, a message whose signature does not hold
        gate.open(_signed(b"x%d" % k, -k)[:-64] + bytes(64), KEY, t + k * 10**9)
    assert gate.silence_warning(t + 9 * 10**9) is None
    warning = gate.silence_warning(t + 10 * 10**9)
    assert warning.startswith("WARNING: nothing received verified for 10 s (11 refused: bad_signature 11)")
    assert gate.silence_warning(t + 11 * 10**9) is None  # once
    assert gate.open(_signed(b"ok", -11.0), KEY, t + 11 * 10**9) == b"ok"  # generated when received
    gate.open(b"\x94unsigned", KEY, t + 12 * 10**9)
    assert gate.silence_warning(t + 21 * 10**9) is None  # a verified message restarted the count
    assert "(1 refused: unsigned 1)" in gate.silence_warning(t + 22 * 10**9)
    off, _ = _gate("off")
    off.open(b"\x94plain", KEY, t)
    assert off.silence_warning(t + 60 * 10**9) is None  # nothing is verified under off: nothing to warn about


def test_the_silence_warning_names_a_foreign_ca():
    foreign, foreign_ids = memory_site(NOW_NS - 86_400 * 10**9, ["rsu1"], [])
    gate, _ = _gate()
    data = Signer(foreign_ids["rsu1"]).sign(b"x", NOW_NS + OFFSET_NS, KEY)
    gate.open(data, KEY, NOW_NS)
    assert "another site's CA" in gate.silence_warning(NOW_NS + 10 * 10**9)


def test_the_intake_screen_refuses_bytes_without_an_envelope_only_under_strict():
    genuine = _signed(b"x", 0.0)
    assert envelope_screen("strict")(b"\x94plain") == "security_unsigned" and envelope_screen("strict")(genuine) is None
    assert envelope_screen("permissive")(b"\x94plain") is None and envelope_screen("off")(b"\x94plain") is None
