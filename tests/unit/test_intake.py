"""Bounded, rate-limited hand-over from Zenoh callbacks to a service loop; the throttled log."""

import sys
import threading

import pytest

from v2i.runtime.intake import Intake, TokenBucket
from v2i.runtime.process import ThrottledLog

S = 1_000_000_000


class FakeClock:
    def __init__(self):
        self.t_ns = 0

    def __call__(self) -> int:
        return self.t_ns


def put(intake: Intake, source: str, payload: bytes = b"x", kind: str = "rsu") -> bool:
    return intake.put(kind, source, len(payload), 0, lambda: payload)


def test_token_bucket_allows_the_burst_then_the_rate():
    bucket = TokenBucket(rate_hz=10.0, burst=3, now_ns=0)
    assert [bucket.take(0) for _ in range(4)] == [True, True, True, False]
    assert not bucket.take(S // 20)  # half a token after 50 ms
    assert bucket.take(S // 10) and not bucket.take(S // 10)
    assert bucket.take(10 * S, cost=3.0) and not bucket.take(10 * S)  # refilled to the burst, no more
    assert not TokenBucket(1.0, 100, 0).take(0, cost=101.0)


def test_oversized_payloads_are_refused_unread():
    intake = Intake(max_bytes=10)
    read = []
    assert not intake.put("rsu", "k", 11, 0, lambda: read.append(1) or b"")
    assert read == [] and intake.take_counts() == {"too_large": 1} and len(intake) == 0


def test_each_source_is_rate_limited_on_its_own():
    clock = FakeClock()
    intake = Intake(rate_hz=5.0, burst=2, clock_ns=clock)
    assert [put(intake, "flood") for _ in range(5)] == [True, True, False, False, False]
    assert put(intake, "genuine") and put(intake, "genuine")
    clock.t_ns = S  # a second later: five more tokens, two of them usable (the burst)
    assert [put(intake, "flood") for _ in range(3)] == [True, True, False]
    assert intake.take_counts() == {"rate_limited": 4} and intake.take_counts() == {}


def test_a_full_queue_drops_the_oldest_of_the_largest_queue():
    intake = Intake(capacity=4, rate_hz=1e9, burst=1000)
    put(intake, "genuine", b"g0")
    for k in range(5):
        put(intake, "flood", b"f%d" % k)
    assert intake.take_counts() == {"queue_full": 2} and len(intake) == 4
    got = [intake.get(0).payload for _ in range(4)]
    assert sorted(got) == [b"f2", b"f3", b"f4", b"g0"]  # the flooder lost its two oldest, the genuine kept its one


def test_byte_budget_is_enforced():
    intake = Intake(capacity=100, max_queued_bytes=10, rate_hz=1e9, burst=1000)
    for k in range(4):
        put(intake, f"s{k}", b"12345")
    assert len(intake) == 2 and intake.take_counts() == {"queue_full": 2}


def test_sources_are_served_round_robin_preferred_first():
    intake = Intake(rate_hz=1e9, burst=1000, preferred=lambda source: source == "rsu1")
    for k in range(3):
        put(intake, "flood", b"f%d" % k)
    put(intake, "other", b"o0")
    put(intake, "rsu1", b"r0")
    put(intake, "rsu1", b"r1")
    order = [intake.get(0).payload for _ in range(6)]
    assert order == [b"r0", b"r1", b"f0", b"o0", b"f1", b"f2"]
    assert intake.get(0) is None


def test_a_waiting_loop_wakes_when_a_payload_arrives():
    intake = Intake()
    got = []
    loop = threading.Thread(target=lambda: got.append(intake.get(5.0)))
    loop.start()
    put(intake, "k", b"hello")
    loop.join(5.0)
    assert got and got[0].payload == b"hello" and got[0].kind == "rsu"


def test_throttled_log_reports_first_refusal_then_one_summary_per_interval(capsys):
    clock = FakeClock()
    log = ThrottledLog("obu", interval_s=10.0, clock_s=lambda: clock.t_ns / S)
    log.refused("malformed", "payload is not msgpack", 1)
    for _ in range(1000):
        log.refused("malformed", "again")
    log.refused("stale", "old list", 5)
    assert capsys.readouterr().err.count("\n") == 2  # the first of each reason, nothing else yet
    clock.t_ns = 10 * S
    log.flush()
    lines = capsys.readouterr().err.splitlines()
    assert lines == ["[obu] refused in the last 10 s: malformed 1000, stale 4"]
    log.flush(force=True)
    assert capsys.readouterr().err == ""  # nothing new to say
    with pytest.raises(TypeError):
        log.refused("x")  # the first refusal's detail is required


def test_memory_trim_runs_at_most_once_a_period():
    from v2i.runtime.process import MemoryTrim, limit_malloc_arenas

    clock = FakeClock()
    trim = MemoryTrim(period_s=5.0, clock_s=lambda: clock.t_ns / S)
    calls = []
    trim._trim = calls.append  # count the calls instead of trimming
    assert not trim.maybe() and calls == []
    clock.t_ns = 5 * S
    assert trim.maybe() and not trim.maybe() and calls == [0]
    clock.t_ns = 10 * S
    assert trim.maybe() and calls == [0, 0]
    assert limit_malloc_arenas() == sys.platform.startswith("linux")  # glibc's mallopt took it


def test_throttled_log_takes_a_services_counters_as_they_grow(capsys):
    clock = FakeClock()
    log = ThrottledLog("rsu", interval_s=10.0, clock_s=lambda: clock.t_ns / S)
    log.totals({"malformed": 3}, {"malformed": "not msgpack"}, "time quer(ies)")
    log.totals({"malformed": 3}, {})  # nothing new
    log.totals({"malformed": 5, "too_large": 2}, {})
    clock.t_ns = 10 * S
    log.totals({"malformed": 5, "too_large": 2}, {})
    assert capsys.readouterr().err.splitlines() == [
        "[rsu] refused (malformed): not msgpack; further refusals are summarised every 10 s",
        "[rsu] refused (too_large): 2 input(s); further refusals are summarised every 10 s",
        "[rsu] refused in the last 10 s: malformed 4, too_large 1",
    ]


def test_signed_kinds_meet_only_the_unverified_budget_which_failures_alone_draw():
    clock = FakeClock()
    intake = Intake(rate_hz=5.0, burst=2, clock_ns=clock, signed_kinds=frozenset({"rsu"}), unverified_rate_hz=10.0,
                    unverified_burst=3, preferred=lambda source: source.startswith("v2x/rsu/"))  # registered RSUs
    # a verified signer's messages never draw from it: 100 at once all pass (their budget is the signer's, later)
    assert all(put(intake, "v2x/rsu/rsu1/objects") for _ in range(100))
    # each failed verification spends a token; once spent, the source's signed messages are refused unread
    for _ in range(3):
        intake.charge_unverified("v2x/rsu/rsu1/objects")
    read = []
    assert not intake.put("rsu", "v2x/rsu/rsu1/objects", 1, 0, lambda: read.append(1) or b"x") and read == []
    assert put(intake, "v2x/rsu/rsu2/objects")  # another source keeps its own
    clock.t_ns = S // 10  # one token back
    assert put(intake, "v2x/rsu/rsu1/objects")
    # kinds not verified keep the per-source rate at the door
    assert [put(intake, "v2x/rsu/rsu1/objects", kind="sensor_pose") for _ in range(3)] == [True, True, False]
    assert intake.take_counts() == {"unverified_budget": 1, "rate_limited": 1}


def test_a_failure_debt_must_be_paid_before_the_source_passes_again():
    clock = FakeClock()
    intake = Intake(clock_ns=clock, signed_kinds=frozenset({"rsu"}), unverified_rate_hz=10.0, unverified_burst=2)
    for _ in range(4):  # failures already queued when the budget ran out: a debt of 2, down to -burst at most
        intake.charge_unverified("k")
    clock.t_ns = 3 * S // 10  # 3 tokens back: 1 of them left after the debt
    assert put(intake, "k")
    intake.charge_unverified("k")
    assert not put(intake, "k")


def test_a_flood_on_other_keys_cannot_spend_a_preferred_sources_unverified_budget():
    clock = FakeClock()
    intake = Intake(clock_ns=clock, signed_kinds=frozenset({"rsu"}), unverified_rate_hz=100.0, unverified_burst=5,
                    unverified_total_hz=10.0, preferred=lambda source: source == "registered")
    for k in range(10):  # ten keys, each within its own budget, together over the shared one
        intake.charge_unverified(f"fake{k}")
    assert not put(intake, "fake-new") and put(intake, "registered")
    assert intake.take_counts() == {"unverified_budget": 1}
    assert not intake.crowded_within(S)  # refusing a non-preferred source crowds nothing out


def test_refusing_a_preferred_sources_message_is_timed_as_crowding_out():
    clock = FakeClock()
    intake = Intake(rate_hz=1.0, burst=1, clock_ns=clock, preferred=lambda source: source == "registered")
    assert put(intake, "registered", kind="sensor_pose") and not intake.crowded_within(S)
    assert not put(intake, "registered", kind="sensor_pose")  # over its rate
    clock.t_ns = S // 2
    assert intake.crowded_within(S) and not intake.crowded_within(S // 4)


def test_a_screened_payload_is_refused_before_the_queue_at_no_cost_to_the_unverified_budget():
    clock = FakeClock()
    intake = Intake(clock_ns=clock, signed_kinds=frozenset({"rsu"}), unverified_rate_hz=10.0, unverified_burst=2,
                    screen=lambda data: None if data.startswith(b"ENV") else "security_unsigned")
    assert not any(put(intake, "k", b"junk") for _ in range(10)) and len(intake) == 0
    assert put(intake, "k", b"ENV-forged?") and len(intake) == 1  # left to the verifier
    assert put(intake, "sensor", b"junk", kind="sensor_pose")  # only signed kinds are screened
    intake.charge_unverified("k")
    intake.charge_unverified("k")  # what the verifier refused spends the budget
    assert not put(intake, "k", b"ENV-genuine")
    assert intake.take_counts() == {"security_unsigned": 10, "unverified_budget": 1}
    assert not intake.crowded_within(S)  # junk refused for what it is crowds nothing out
