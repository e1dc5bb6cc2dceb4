"""v2i.telemetry.latency.StageLatency: quantiles, histogram, thread safety, invalid inputs."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from v2i.telemetry.latency import BUCKETS_S, MAX_STAGES, RING_SIZE, TOO_MANY_STAGES, StageLatency


def test_buckets_are_log_spaced_from_100_us_to_10_s():
    assert BUCKETS_S[0] == pytest.approx(1e-4) and BUCKETS_S[-1] == pytest.approx(10.0)
    assert 18 <= len(BUCKETS_S) <= 24
    ratios = np.diff(np.log10(BUCKETS_S))
    assert np.all(ratios > 0.2) and np.all(ratios < 0.3)


def test_quantiles_equal_numpy_percentile_on_the_same_samples():
    rng = np.random.default_rng(7)
    samples_s = rng.lognormal(np.log(2e-3), 0.8, size=1000)
    latency = StageLatency()
    for s in samples_s:
        latency.observe("decode", float(s))
    summary = latency.summary_ms()["decode"]
    assert summary["count"] == 1000
    for label, q in (("p50", 50), ("p95", 95), ("p99", 99)):
        assert summary[label] == pytest.approx(np.percentile(samples_s, q) * 1e3, abs=5e-4)


def test_quantiles_cover_only_the_latest_ring_but_count_everything():
    latency = StageLatency(ring_size=100)
    for _ in range(500):
        latency.observe("put", 1.0)  # old, slow
    for i in range(100):
        latency.observe("put", 1e-3 * (i + 1))
    summary = latency.summary_ms()["put"]
    assert summary["count"] == 600
    assert summary["p99"] < 101.0  # the 1 s samples left the ring
    assert summary["p50"] == pytest.approx(np.percentile(np.arange(1, 101), 50), abs=1e-3)
    _, sum_s, count = latency.histogram("put")
    assert count == 600 and sum_s == pytest.approx(500 + 1e-3 * 5050)


def test_histogram_counts_are_cumulative_with_le_semantics():
    latency = StageLatency()
    values_s = [0.0, 5e-5, 1e-4, 1.5e-4, 0.002, 0.5, 10.0, 11.0, 200.0]
    for v in values_s:
        latency.observe("fuse", v)
    cumulative, sum_s, count = latency.histogram("fuse")
    assert len(cumulative) == len(BUCKETS_S) + 1
    assert cumulative == [sum(v <= b for v in values_s) for b in BUCKETS_S] + [len(values_s)]
    assert cumulative[0] == 3  # 0, 50 us and exactly 100 us (le: a value on a bound counts in it)
    assert all(a <= b for a, b in zip(cumulative, cumulative[1:]))
    assert count == len(values_s) and sum_s == pytest.approx(sum(values_s))


def test_unknown_stage_histogram_is_zero_and_summary_leaves_it_out():
    latency = StageLatency()
    assert latency.histogram("nothing") == ([0] * (len(BUCKETS_S) + 1), 0.0, 0)
    assert latency.summary_ms() == {}


def test_nan_inf_and_negative_are_refused_and_counted():
    latency = StageLatency()
    for bad in (float("nan"), float("inf"), -1e-6, -5.0):
        latency.observe("rsu_to_obu", bad)
    latency.observe("rsu_to_obu", 0.004)
    assert latency.invalid() == {"rsu_to_obu": 4}
    assert latency.histogram("rsu_to_obu")[2] == 1
    assert latency.summary_ms()["rsu_to_obu"] == {"count": 1, "p50": 4.0, "p95": 4.0, "p99": 4.0}


def test_stage_with_only_invalid_values_is_listed_but_not_summarised():
    latency = StageLatency()
    latency.observe("queue", float("nan"))
    assert latency.stages() == ["queue"]
    assert latency.summary_ms() == {}


def test_observe_ns_converts_to_seconds():
    latency = StageLatency()
    latency.observe_ns("encode", 1_000_000, 3_500_000)
    assert latency.summary_ms()["encode"]["p50"] == pytest.approx(2.5)
    latency.observe_ns("encode", 5, 4)
    assert latency.invalid() == {"encode": 1}


def test_stage_names_are_bounded():
    latency = StageLatency()
    for i in range(MAX_STAGES + 5):
        latency.observe(f"s{i}", 1e-3)
    assert len(latency.stages()) == MAX_STAGES
    assert latency.invalid() == {TOO_MANY_STAGES: 5}


def test_ring_size_must_be_positive():
    with pytest.raises(ValueError):
        StageLatency(ring_size=0)
    assert RING_SIZE >= 1000


def test_two_threads_lose_no_observation():
    latency = StageLatency(ring_size=50_000)
    n = 20_000
    start = threading.Barrier(3)

    def worker(stage: str, value_s: float) -> None:
        start.wait()
        for _ in range(n):
            latency.observe(stage, value_s)
            latency.observe("shared", value_s)

    threads = [threading.Thread(target=worker, args=("a", 1e-3)), threading.Thread(target=worker, args=("b", 2e-3))]
    for t in threads:
        t.start()
    start.wait()
    for _ in range(50):  # readers meanwhile
        latency.summary_ms()
        latency.histogram("shared")
    for t in threads:
        t.join()
    assert latency.histogram("a")[2] == n and latency.histogram("b")[2] == n
    cumulative, sum_s, count = latency.histogram("shared")
    assert count == 2 * n and cumulative[-1] == 2 * n
    assert sum_s == pytest.approx(n * 3e-3)
    assert latency.summary_ms()["shared"]["count"] == 2 * n


# ---- the wire: latency_ms in ObuMetrics / RsuMetrics ------------------------------------------

T_NS = 1_700_000_000_000_000_000


def _metrics_with(latency_ms):
    from schemas.messages import ObuMetrics

    return ObuMetrics(vehicle_id="ego", t_ns=T_NS, latency_ms=latency_ms)


def test_summary_round_trips_in_obu_and_rsu_metrics():
    from schemas.codec import decode, encode
    from schemas.messages import ObuMetrics, RsuMetrics

    latency = StageLatency()
    for v in (1e-3, 2e-3, 4e-3):
        latency.observe("fuse", v)
        latency.observe("put", v / 10)
    summary = latency.summary_ms()
    obu = decode(encode(ObuMetrics(vehicle_id="ego", t_ns=T_NS, latency_ms=summary)), ObuMetrics)
    rsu = decode(encode(RsuMetrics(rsu_id="rsu1", t_ns=T_NS, latency_ms=summary)), RsuMetrics)
    for msg in (obu, rsu):
        assert {k: v.model_dump() for k, v in msg.latency_ms.items()} == summary


def test_messages_without_latency_still_decode():
    import msgpack

    from schemas.codec import decode
    from schemas.messages import SCHEMA_VERSION, ObuMetrics, RsuMetrics

    for model, body in ((ObuMetrics, {"vehicle_id": "ego", "t_ns": T_NS, "cycles": 3}),
                        (RsuMetrics, {"rsu_id": "rsu1", "t_ns": T_NS, "published": 2})):
        data = msgpack.packb({"v": SCHEMA_VERSION, "t": model.TYPE, "d": body}, use_bin_type=True)
        assert decode(data, model).latency_ms == {}


@pytest.mark.parametrize("latency_ms", [
    {"fuse": {"count": 1, "p50": 2.0, "p95": 1.0, "p99": 3.0}},  # out of order
    {"fuse": {"count": 1, "p50": -1.0, "p95": 1.0, "p99": 3.0}},  # negative
    {"fuse": {"count": 1, "p50": float("nan"), "p95": 1.0, "p99": 3.0}},
    {"fuse": {"count": -1, "p50": 1.0, "p95": 1.0, "p99": 1.0}},
    {"fuse": {"count": 1, "p50": 1.0, "p95": 1.0, "p99": 1.0, "extra": 1}},
    {"Bad Name": {"count": 1, "p50": 1.0, "p95": 1.0, "p99": 1.0}},
    {f"s{i}": {"count": 1, "p50": 1.0, "p95": 1.0, "p99": 1.0} for i in range(MAX_STAGES + 1)},  # unbounded
])
def test_bad_latency_fields_are_refused(latency_ms):
    from pydantic import ValidationError

    with pytest.raises(ValidationError):
        _metrics_with(latency_ms)


def test_bad_latency_on_the_wire_is_a_codec_error():
    import msgpack

    from schemas.codec import CodecError, decode
    from schemas.messages import SCHEMA_VERSION, ObuMetrics

    body = {"vehicle_id": "ego", "t_ns": T_NS, "latency_ms": {"fuse": {"count": 1, "p50": 5.0, "p95": 1.0, "p99": 1.0}}}
    with pytest.raises(CodecError):
        decode(msgpack.packb({"v": SCHEMA_VERSION, "t": "obu_metrics", "d": body}, use_bin_type=True), ObuMetrics)


def test_periodic_summary_recomputes_once_per_period():
    from v2i.telemetry.latency import PeriodicSummary

    latency = StageLatency()
    latency.observe("fuse", 1e-3)
    periodic = PeriodicSummary(latency, period_ns=1_000)
    first = periodic.get(10_000)
    latency.observe("fuse", 1e-3)
    assert periodic.get(10_999) is first and first["fuse"]["count"] == 1
    assert periodic.get(11_000)["fuse"]["count"] == 2
    latency.observe("fuse", 1e-3)
    assert periodic.get(5_000)["fuse"]["count"] == 3  # the clock went back: recomputed
