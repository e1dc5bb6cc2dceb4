import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from obu_service.clock_sync import ClockSync, SyncSample

T0 = 1_767_225_600 * 10**9


def exchange(t1, theta, up_ns, down_ns, hold_ns=50_000):
    t2 = t1 + up_ns + theta
    t3 = t2 + hold_ns
    t4 = t3 - theta + down_ns
    return SyncSample(t1, t2, t3, t4)


def test_single_exchange_formulas():
    s = exchange(T0, theta=350_000_000, up_ns=10_000_000, down_ns=30_000_000)
    assert s.round_trip_ns == 40_000_000
    # error of one sample = (up - down) / 2
    assert s.offset_ns - 350_000_000 == (10_000_000 - 30_000_000) // 2


@settings(max_examples=60, deadline=None)
@given(theta_ms=st.floats(-2000, 2000), seed=st.integers(0, 2**32 - 1))
def test_min_delay_filter_uses_least_delayed_sample(theta_ms, seed):
    rng = np.random.default_rng(seed)
    sync = ClockSync(window=16)
    theta = round(theta_ms * 1e6)
    samples = []
    for k in range(16):
        up, down = 5_000_000 + rng.exponential(20e6), 5_000_000 + rng.exponential(20e6)
        samples.append(exchange(T0 + k * 500_000_000, theta, round(up), round(down)))
        sync.add(samples[-1])
    est = sync.estimate()
    assert abs(est.offset_ns - theta) <= est.uncertainty_ns + 1  # the bound is honest
    assert est.uncertainty_ns == min(s.round_trip_ns for s in samples) // 2
    assert sync.naive().offset_ns == samples[-1].offset_ns


def test_rejects_inconsistent_and_converts_times():
    sync = ClockSync()
    assert sync.to_obu_ns(T0) is None
    assert not sync.add(SyncSample(T0, T0, T0 + 10, T0 - 1))
    assert sync.add(exchange(T0, theta=1_000_000_000, up_ns=1_000_000, down_ns=1_000_000))
    assert sync.to_obu_ns(T0 + 1_000_000_000) == pytest.approx(T0, abs=1)
