"""The compiled clock statistics (v2i.clock.clock_envelope) equal their numpy / scipy definitions
(v2i.clock.envelope_reference), the whole window fit included."""

import math

import numpy as np
import pytest
from scipy.stats import theilslopes

from v2i.clock import envelope_reference as ref
from v2i.clock.clock_envelope import (QUEUED_NS, _order, _quantile, _tail_mean_sd, consensus, fit_drift, fit_window,
                                        leg_envelope, shared_slope, theil_sen_slope)

PRIOR = (0.0, 100_000.0)  # ns/s: 0 +- 100 ppm


# --- windows -------------------------------------------------------------------------------------

def window(rng, n, drift_ns_per_s=40_000.0, segments=1):
    """n exchanges at ~10 Hz ending at t = 0: (t_up, z_up, t_down, z_down, group) with queued
    readings, a congested stretch and, with segments > 1, clock steps between segments."""
    t_up = np.sort(-np.arange(n)[::-1] * 0.1 - rng.uniform(0, 0.02, n))
    t_down = t_up + rng.uniform(0.02, 0.06, n)
    group = np.minimum(np.arange(n) * segments // n, segments - 1)
    steps = np.array([0.0, 3e8, -2e8])[group]
    z_up = drift_ns_per_s * t_up + steps + rng.exponential(2e6, n) + 1e6
    z_down = -drift_ns_per_s * t_down - steps + rng.exponential(2e6, n) + 1e6
    queued = rng.random(n) < 0.03
    z_up[queued] += QUEUED_NS * 1.5
    congested = (t_down > t_down[n // 2]) & (t_down < t_down[n // 2] + 2.5)
    z_down[congested] += 8e6
    outside = rng.random(n) < 0.05
    return t_up, z_up, t_down, z_down, np.where(outside, -1, group)


def legs_of(t_up, z_up, t_down, z_down, group):
    return [leg for g in range(group.max() + 1) for leg in ((t_up[group == g], z_up[group == g], 1.0),
                                                           (t_down[group == g], z_down[group == g], -1.0))]


# --- the tests ------------------------------------------------------------------------------------

def test_the_sort_and_quantiles_equal_numpy():
    rng = np.random.default_rng(5)
    for n in range(1, 80):
        for x in (rng.normal(0.0, 1e6, n), rng.integers(-5, 5, n).astype(float), np.full(n, 2.5e5)):
            assert np.array_equal(_order(x), np.argsort(x, kind="stable"))
            s = np.sort(x)
            for p in (0.25, 0.5):
                assert _quantile(s, p) == pytest.approx(np.percentile(x, 100 * p), rel=1e-12, abs=1e-9)
            assert _tail_mean_sd(x, 0.1) == pytest.approx(ref.tail_mean_sd(x, 0.1), rel=1e-9, abs=1e-6)


def test_shared_slope_and_theil_sen_equal_the_library_fits():
    """The weighted shared slope equals np.linalg.lstsq on rows scaled by sqrt(w) (equal weights: the plain
    fit), Theil-Sen scipy's."""
    rng = np.random.default_rng(11)
    groups = [np.sort(rng.uniform(-60, 0, n)) for n in (7, 12, 5)]
    ys = [3.0 * t + c + rng.normal(0, 0.5, len(t)) for t, c in zip(groups, (10.0, -4.0, 100.0))]
    t, y, first = np.concatenate(groups), np.concatenate(ys), np.array([0, 7, 19, 24])
    for w in (np.ones(len(t)), rng.integers(1, 21, len(t)).astype(float)):
        ok, d, se = shared_slope(t, y, w, first, 0.0)
        want = ref.shared_slope([list(zip(a, b, c)) for a, b, c in zip(groups, ys, np.split(w, first[1:-1]))], 0.0)
        assert ok and d == pytest.approx(want[0], rel=1e-9) and se == pytest.approx(want[1], rel=1e-9)
    assert theil_sen_slope(groups[1], ys[1], np.array([0, 12])) == pytest.approx(theilslopes(ys[1], groups[1]).slope,
                                                                                  rel=1e-12)
    assert not shared_slope(t[:9], y[:9], w[:9], np.array([0, 7, 9]), 0.0)[0]  # only one group of >= 3


def test_fit_drift_and_the_leg_envelope_equal_their_numpy_definitions():
    """Random windows with queued readings, a congested stretch, exchanges left out and up to three
    clock segments: the same drift, sd and envelope to rounding."""
    rng = np.random.default_rng(3)
    fitted = 0
    for trial in range(60):
        n, segments = int(rng.integers(5, 400)), int(rng.integers(1, 4))
        t_up, z_up, t_down, z_down, group = window(rng, n, segments=segments)
        phase = float(rng.uniform(0, 2))
        got = fit_drift(t_up, z_up, t_down, z_down, group, 2.0, phase, 0.1, *PRIOR, 50_000.0)
        want = ref.fit_drift(legs_of(t_up, z_up, t_down, z_down, group), 2.0, phase, 0.1, PRIOR, 50_000.0)
        assert got == pytest.approx(want, rel=1e-9, abs=1e-6)
        fitted += got != PRIOR
        mine = group == group.max()
        for t, z, sign in ((t_up[mine], z_up[mine], 1), (t_down[mine], z_down[mine], -1)):
            args = (sign, got[0], 3 * got[1], 0.1, float(rng.choice([2.0, 10.0, 30.0])), 2e6)
            assert leg_envelope(t, z, *args, 3) == pytest.approx(ref.leg_envelope(t, z, *args), rel=1e-9, abs=1e-6)
    assert fitted > 40  # most windows are old enough for a fit (the rest: the prior, on both sides)


def test_a_young_window_fits_the_prior_and_three_bins_on_two_legs_fit_the_readings():
    """fit_drift needs two legs with >= 3 bins (a shared slope with an intercept per leg): with
    fewer it is the prior exactly; from then on the readings' slope (40 ppm = 40 us/s) shows."""
    rng = np.random.default_rng(4)
    young = window(rng, 39)  # 3.9 s: at most 2 bins of 2 s per leg
    assert fit_drift(*young, 2.0, 0.0, 0.1, *PRIOR, 50_000.0) == PRIOR
    drift, sd = fit_drift(*window(rng, 200), 2.0, 0.0, 0.1, *PRIOR, 50_000.0)
    assert sd < PRIOR[1] and abs(drift - 40_000.0) < 3 * sd


def test_the_half_filled_bin_at_a_window_s_edge_counts_by_its_readings():
    """4.4 s of readings at 10 Hz over bins of 2 s with edges at -4.0 and -2.0 s: the oldest bin holds
    4 readings, the others 20. That bin is the fit's third (it used to be dropped as half-filled,
    leaving the prior): weighted by its count, the drift shows (40 ppm = 40 us/s) within 3 sd, and
    the fit equals its numpy definition."""
    rng = np.random.default_rng(6)
    drift = 40_000.0  # ns/s
    t_up = -np.arange(44)[::-1] * 0.1 - 0.0015
    t_down = t_up + 0.001
    z_up = drift * t_up + rng.exponential(3e5, 44) + 1e6
    z_down = -drift * t_down + rng.exponential(3e5, 44) + 1e6
    group = np.zeros(44, np.int64)
    bins = np.floor((t_up + 1.999) / 2.0)
    assert sorted(np.unique(bins, return_counts=True)[1]) == [4, 20, 20]
    got = fit_drift(t_up, z_up, t_down, z_down, group, 2.0, 1.999, 0.1, *PRIOR, 50_000.0)
    assert got != PRIOR and got[1] < PRIOR[1] / 2 and abs(got[0] - drift) < 3 * got[1]
    want = ref.fit_drift(legs_of(t_up, z_up, t_down, z_down, group), 2.0, 1.999, 0.1, PRIOR, 50_000.0)
    assert got == pytest.approx(want, rel=1e-9, abs=1e-6)


def test_consensus_equals_the_lexsort_of_openings_before_closings():
    """Ties everywhere (integer readings: an opening and a closing at the same value, equal
    openings), every exchange or a subset voting, a few exchanges or many: the same agreement."""
    rng = np.random.default_rng(21)
    for _ in range(400):
        n = int(rng.integers(1, 60))
        t1 = np.sort(rng.integers(-60, 1, n)).astype(float)
        args = (t1, rng.integers(-5, 6, n).astype(float), t1 + 0.01, rng.integers(-5, 6, n).astype(float),
                float(rng.choice([0.0, 0.5, -1.25])), rng.integers(0, 3, n).astype(float))
        among = np.ones(n, bool) if rng.random() < 0.5 else rng.random(n) < 0.7
        among[0] = True
        assert np.array_equal(consensus(*args, among), ref.consensus(*args, among))


def test_the_sort_s_shortcuts_and_the_k_least_equal_numpy_s_stable_argsort():
    """_order's shortcuts (readings by time, ages by time) and _lowest (the k least, stable) give
    np.argsort(kind="stable") exactly: sorted, reversed, tied, constant, random, -0.0 beside 0.0 and
    NaN inputs (_lowest: its first k, for every k)."""
    from v2i.clock.clock_envelope import _lowest

    rng = np.random.default_rng(17)
    for n in range(1, 120):
        ties = rng.integers(-4, 4, n).astype(float)
        zeros = rng.choice([0.0, -0.0, 1.0], n)
        rising = np.cumsum(rng.integers(0, 3, n)).astype(float)  # non-decreasing, with ties
        for x in (rng.normal(0.0, 1e6, n), ties, zeros, np.full(n, 2.5e5), rising, -rising, rising[::-1].copy(),
                  np.sort(rng.normal(size=n))[::-1].copy(), np.sort(ties), np.sort(ties)[::-1].copy()):
            want = np.argsort(x, kind="stable")
            assert np.array_equal(_order(x), want), (n, x)
            for k in {1, n, max(1, n // 10), int(rng.integers(1, n + 1))}:
                assert np.array_equal(_lowest(x, k), want[:k]), (n, k, x)
        x = rng.normal(size=n)
        x[rng.integers(0, n)] = np.nan  # _lowest falls back to _order
        for k in (1, n):
            assert np.array_equal(_lowest(x, k), _order(x)[:k])


def exchanges(rng, n, segments):
    """n four-timestamp exchanges at ~10 Hz (times (n, 4) int64 ns, segment (n,)): an RSU clock 2 s ahead
    drifting by 40 ppm, stepping between segments, exponential delays, a few queued replies and forgeries."""
    t1 = 1_700_000_000 * 10**9 + np.cumsum(rng.integers(90, 110, n)) * 10**6
    segment = np.minimum(np.arange(n) * segments // n, segments - 1)
    theta = 2e9 + 40e3 * (t1 - t1[0]) / 1e9 + np.array([0.0, 3e8, -2e8])[segment]
    up, down = rng.exponential(3e6, n) + 1e6, rng.exponential(3e6, n) + 1e6
    down[rng.random(n) < 0.03] += 3e8  # a reply queued for a while
    t2 = t1 + up + theta
    t3 = t2 + rng.integers(10_000, 200_000, n)
    t4 = t3 - theta + down
    forged = rng.random(n) < 0.04
    t2[forged] += rng.choice([-1.0, 1.0], forged.sum()) * 5e7  # replies that disagree
    return np.column_stack([t1, t2, t3, t4]).astype(np.int64), segment.astype(np.int64)


def test_fit_window_equals_its_numpy_reference():
    """The whole compiled window fit against envelope_reference.fit_window on windows of 1-300 exchanges over up
    to three clock segments with queued and forged replies, young and old fits: the same exchanges left out and
    the same arming, every number to rounding."""
    rng = np.random.default_rng(8)
    armed = 0
    for trial in range(120):
        n, segments = int(rng.integers(1, 300)), int(rng.integers(1, 4))
        times, segment = exchanges(rng, n, min(segments, n))
        prev = (float(rng.choice([0.0, 35e3])), float(rng.choice([100e3, 5e3])))
        args = (times, segment, *prev, 0.0, 100e3, 2 * 10**9, 0.1, 500e3, 3.0, 30.0, 2e6, 10, 30, 50e3)
        got, want = fit_window(*args), ref.fit_window(*args)
        assert np.array_equal(got[0], want[0]) and got[10] == want[10] and got[1] == want[1], trial
        assert got[7] == want[7] and got[9] == want[9], trial  # the t1 and t4 of the least readings
        for a, b in zip(got[2:10], want[2:10]):
            assert a == pytest.approx(b, rel=1e-9, abs=1e-3), trial
        armed += got[10]
    assert 10 < armed < 110  # both young and armed windows
