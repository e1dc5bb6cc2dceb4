import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from obu_service.clock_sync import ClockSync, SyncSample
from obu_service.sync_sim import LTE_DOWNLINK, LTE_UPLINK, exchanges, run_sync
from sim.clock import ClockStep, DriftingClock, SimClock

T0 = 1_767_225_600 * 10**9
S, MS = 10**9, 10**6


def exchange(t1, theta, up_ns, down_ns, hold_ns=50_000):
    t2 = t1 + up_ns + theta
    t3 = t2 + hold_ns
    t4 = t3 - theta + down_ns
    return SyncSample(t1, t2, t3, t4)


def lte_run(offset_ns, drift_ppm, seed, duration_s=60, steps=()):
    """The scoring set-up: LTE-V2X legs (medians 21 / 22 ms, spikes, 2-3 % loss), 10 Hz."""
    clock = DriftingClock(SimClock(), offset_ns, drift_ppm, T0, steps)
    samples = exchanges(clock, LTE_UPLINK.draw_ns, LTE_DOWNLINK.draw_ns, np.random.default_rng(seed), T0,
                        duration_s * S)
    return clock, samples


def test_single_exchange_formulas():
    s = exchange(T0, theta=350_000_000, up_ns=10_000_000, down_ns=30_000_000)
    assert s.round_trip_ns == 40_000_000
    # error of one sample = (up - down) / 2
    assert s.offset_ns - 350_000_000 == (10_000_000 - 30_000_000) // 2
    assert s.brackets(350_000_000) and not s.brackets(350_000_000 + 11 * MS)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(theta_ms=st.floats(-2000, 2000), seed=st.integers(0, 2**32 - 1))
def test_bound_is_honest_and_naive_is_the_last_sample(theta_ms, seed):
    rng = np.random.default_rng(seed)
    sync = ClockSync(window=16)
    theta = round(theta_ms * 1e6)
    samples = []
    for k in range(16):
        up, down = 5_000_000 + rng.exponential(20e6), 5_000_000 + rng.exponential(20e6)
        samples.append(exchange(T0 + k * 500_000_000, theta, round(up), round(down)))
        assert sync.add(samples[-1])
    est = sync.estimate()
    assert abs(est.offset_ns - theta) <= est.uncertainty_ns + 1  # the bound is honest
    assert est.uncertainty_ns <= np.median([s.round_trip_ns for s in samples]) / 2  # from the low tail
    assert sync.naive().offset_ns == samples[-1].offset_ns


def test_rejects_inconsistent_and_converts_times():
    sync = ClockSync()
    assert sync.to_obu_ns(T0) is None and sync.estimate() is None
    assert not sync.add(SyncSample(T0, T0, T0 + 10, T0 - 1))  # t4 < t1
    assert not sync.add(SyncSample(T0, T0 + 5, T0 + 50, T0 + 20))  # round trip 20 - 45 < 0
    assert sync.estimate() is None and sync.naive() is None
    assert sync.add(exchange(T0, theta=1_000_000_000, up_ns=1_000_000, down_ns=1_000_000))
    assert sync.estimate().samples == 1
    assert sync.to_obu_ns(T0 + 1_000_000_000) == pytest.approx(T0, abs=1)


def test_conversions_use_the_drift():
    sync = ClockSync()
    sync.add(exchange(T0, theta=0, up_ns=MS, down_ns=MS))
    est = sync.estimate_at(T0)
    est = type(est)(est.offset_ns, est.uncertainty_ns, est.samples, 100.0, est.at_ns)  # 100 ppm
    assert est.offset_at_ns(T0 + 10 * S) - est.offset_ns == 1 * MS  # 100 ppm of 10 s = 1 ms
    rsu = est.to_rsu_ns(T0 + 10 * S)
    assert est.to_obu_ns(rsu) == pytest.approx(T0 + 10 * S, abs=1)


@settings(max_examples=15, deadline=None, derandomize=True)
@given(offset_ms=st.floats(-2000, 2000), drift_ppm=st.floats(-100, 100), seed=st.integers(0, 2**16))
def test_any_offset_and_drift_is_recovered(offset_ms, drift_ppm, seed):
    """Stated bound: after 20 s of 10 Hz LTE-V2X exchanges, |error| <= 1 ms at the last
    exchange and 1 s later (extrapolated with the drift), and the error is within the
    reported uncertainty."""
    clock, samples = lte_run(round(offset_ms * MS), drift_ppm, seed, duration_s=20)
    sync = ClockSync()
    for s in samples:
        sync.add(s)
    for t in (samples[-1].t4_ns, samples[-1].t4_ns + S):
        est = sync.estimate_at(t)
        err = est.offset_ns - clock.offset_at(t)
        assert abs(err) <= 1 * MS
        assert abs(err) <= est.uncertainty_ns
    assert sync.steps_detected == 0


@pytest.mark.parametrize("offset_ms, drift_ppm, seed", [(1500, 100, 0), (-2000, -100, 1), (300, 37, 2)])
def test_scoring_target_without_step(offset_ms, drift_ppm, seed):
    clock, samples = lte_run(offset_ms * MS, drift_ppm, seed)
    run = run_sync(clock, samples, T0, 60 * S)
    stats = run.stats_ms(after_ns=5 * S)
    assert stats["p95_ms"] <= 1.0
    assert stats["naive_p95_ms"] >= 10 * stats["p95_ms"]  # the naive latest exchange is much worse
    est = ClockSync()
    for s in samples:
        est.add(s)
    assert est.estimate().drift_ppm == pytest.approx(drift_ppm, abs=25)


@pytest.mark.parametrize("step_ms, seed", [(500, 0), (-500, 1), (20, 2)])
def test_clock_step_is_detected_and_recovered_within_3_s(step_ms, seed):
    clock, samples = lte_run(-700 * MS, 60.0, seed, duration_s=30, steps=(ClockStep(T0 + 15 * S, step_ms * MS),))
    run = run_sync(clock, samples, T0, 30 * S)
    assert run.steps_detected == 1
    assert run.reconvergence_ns(15 * S, tol_ns=1 * MS) < 3 * S
    assert run.stats_ms(after_ns=5 * S, until_ns=15 * S)["p95_ms"] <= 1.0


def test_spikes_do_not_move_the_estimate():
    """Replies queued 300 ms move a plain NTP client by ~145 ms; the filter moves no more than
    if those exchanges had been lost."""
    rng = np.random.default_rng(7)
    theta = 123_456_789
    calm = [exchange(T0 + k * S // 10, theta, round(10 * MS + rng.exponential(MS)), round(10 * MS + rng.exponential(MS)))
            for k in range(200)]
    spikes = [exchange(T0 + k * S // 10, theta, round(10 * MS + rng.exponential(MS)), 300 * MS) for k in range(200, 205)]
    spiky, lossy = ClockSync(), ClockSync()
    for s in calm:
        spiky.add(s)
        lossy.add(s)
    for s in spikes:
        spiky.add(s)
    assert abs(spiky.naive().offset_ns - theta) > 100 * MS
    t = T0 + 21 * S
    assert abs(spiky.estimate_at(t).offset_ns - lossy.estimate_at(t).offset_ns) < 10_000
    assert abs(spiky.estimate_at(t).offset_ns - theta) < 200_000
    assert spiky.steps_detected == 0


def test_unconfirmed_outliers_are_given_back_not_a_step():
    sync = ClockSync()
    theta = 0
    for k in range(100):
        sync.add(exchange(T0 + k * S // 10, theta, 10 * MS, 10 * MS))
    # two readings far below the envelope (a +50 ms step would do that) then ordinary ones again
    for k in range(100, 102):
        sync.add(exchange(T0 + k * S // 10, theta + 50 * MS, 10 * MS, 10 * MS))
    assert abs(sync.estimate().offset_ns - theta) < 1000  # held aside: no effect
    for k in range(102, 120):
        sync.add(exchange(T0 + k * S // 10, theta, 10 * MS, 10 * MS))
    assert sync.steps_detected == 0
    # a real step: three in a row
    for k in range(120, 123):
        sync.add(exchange(T0 + k * S // 10, theta + 50 * MS, 10 * MS, 10 * MS))
    assert sync.steps_detected == 1
    assert abs(sync.estimate().offset_ns - (theta + 50 * MS)) < 1000


def test_memory_and_time_window_are_bounded():
    sync = ClockSync(window=100, horizon_ns=5 * S)
    for k in range(1000):
        sync.add(exchange(T0 + k * S // 20, 0, MS, MS))
    assert len(sync._samples) <= 100
    sync = ClockSync(horizon_ns=5 * S)
    for k in range(200):
        sync.add(exchange(T0 + k * S // 10, 0, MS, MS))
    span = sync._samples[-1].t4_ns - sync._samples[0].t4_ns
    assert span <= 5 * S
