"""The compiled clock statistics (obu_service.clock_envelope) equal their numpy / scipy definitions."""

import math

import numpy as np
import pytest
from scipy.stats import theilslopes

from obu_service.clock_envelope import (QUEUED_NS, _order, _quantile, _tail_mean_sd, consensus, fit_drift,
                                        leg_envelope, shared_slope, theil_sen_slope)

PRIOR = (0.0, 100_000.0)  # ns/s: 0 +- 100 ppm


# --- numpy definitions ---------------------------------------------------------------------------

def tail_size(n, q):
    return min(n, max(1, math.ceil(q * n)))


def ref_tail_mean_sd(r, q):
    tail = np.sort(r)[:tail_size(len(r), q)]
    dev = tail - tail[-1]
    return np.sqrt(max(np.mean(dev**2) / q - np.mean(dev) ** 2, 0.0))


def ref_bin_points(t, r, sign, d, bin_s, phase_s, q):
    """(mean t, sign E + d t) of each bin of un-queued readings holding at least half the median count."""
    bins = np.floor((t + phase_s) / bin_s)
    keep = r <= r.min() + QUEUED_NS
    t, r, bins = t[keep], r[keep], bins[keep]
    values, counts = np.unique(bins, return_counts=True)
    points = [(t[bins == v].mean(), sign * np.sort(r[bins == v])[:tail_size(c, q)].mean())
              for v, c in zip(values, counts) if c >= 0.5 * np.median(counts)]
    return [(tb, e + d * tb) for tb, e in points]


def ref_shared_slope(groups, min_resid):
    """Least squares with one slope column and an intercept column per group (np.linalg.lstsq)."""
    groups = [g for g in groups if len(g) >= 2]
    if sum(len(g) >= 3 for g in groups) < 2:
        return None
    design = np.zeros((sum(map(len, groups)), 1 + len(groups)))
    y, row = np.empty(len(design)), 0
    for k, g in enumerate(groups):
        design[row:row + len(g), 0], design[row:row + len(g), 1 + k] = [p[0] for p in g], 1.0
        y[row:row + len(g)] = [p[1] for p in g]
        row += len(g)
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    rss = float(np.sum((y - design @ coef) ** 2))
    sxx = sum(np.sum((np.array([p[0] for p in g]) - np.mean([p[0] for p in g])) ** 2) for g in groups)
    return coef[0], np.sqrt(max(rss / max(1, len(y) - len(groups) - 1), min_resid**2) / sxx)


def ref_fit_drift(legs, bin_s, phase_s, q, prior, min_resid):
    """fit_drift of legs [(t, z, sign)] as its docstring defines it."""
    legs = [leg for leg in legs if len(leg[0]) >= 3]
    if sum(len(np.unique(np.floor((t + phase_s) / bin_s))) >= 3 for t, _, _ in legs) < 2:
        return prior
    (d0, sd0), d = prior, prior[0]
    n = sum(len(t) for t, _, _ in legs)
    for _ in range(2):
        detrended = [z - s * d * t for t, z, s in legs]
        groups = [ref_bin_points(t, r, s, d, bin_s, phase_s, q) for (t, _, s), r in zip(legs, detrended)]
        floor = max(min_resid, max(ref_tail_mean_sd(r, q) for r in detrended)
                    / np.sqrt(max(1.0, n / max(sum(map(len, groups)), 1))))
        slopes = [(b[1] - a[1]) / (b[0] - a[0])
                  for g in groups for i, a in enumerate(g) for b in g[i + 1:] if b[0] != a[0]]
        if slopes:
            robust = np.median(slopes)
            groups = [g if len(g) < 4 else [p for p, e in zip(g, excess) if e <= np.percentile(excess, 25) + 3 * floor]
                      for g, (_, _, s) in zip(groups, legs) for excess in [[s * (y - robust * t) for t, y in g]]]
        fit = ref_shared_slope(groups, floor)
        if fit is None:
            return prior
        s, se = fit
        d, sd = d0 + sd0**2 / (sd0**2 + se**2) * (s - d0), (1 / sd0**2 + 1 / se**2) ** -0.5
    return d, sd


def ref_leg_envelope(t, z, sign, drift, drift_bound, q, horizon_s, margin_ns, min_readings=3):
    r = z - sign * drift * t
    usable = np.flatnonzero(r <= r.min() + QUEUED_NS)
    order = usable[np.argsort(-t[usable], kind="stable")]
    ages, best, h = -t[order], None, horizon_s
    while True:
        rows = order[:max(min(min_readings, len(order)), int(np.searchsorted(ages, h, side="right")))]
        low = rows[np.argsort(r[rows], kind="stable")[:tail_size(len(rows), q)]]
        env = (r[low].mean(), max(0.0, -t[low].mean()))
        if best is None or env[0] + drift_bound * env[1] < best[0] + drift_bound * best[1] - margin_ns:
            best = env
        if h >= ages[-1]:
            return best
        h *= 2.0


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
    return [leg for g in range(group.max() + 1) for leg in ((t_up[group == g], z_up[group == g], 1),
                                                           (t_down[group == g], z_down[group == g], -1))]


# --- the tests ------------------------------------------------------------------------------------

def test_the_sort_and_quantiles_equal_numpy():
    rng = np.random.default_rng(5)
    for n in range(1, 80):
        for x in (rng.normal(0.0, 1e6, n), rng.integers(-5, 5, n).astype(float), np.full(n, 2.5e5)):
            assert np.array_equal(_order(x), np.argsort(x, kind="stable"))
            s = np.sort(x)
            for p in (0.25, 0.5):
                assert _quantile(s, p) == pytest.approx(np.percentile(x, 100 * p), rel=1e-12, abs=1e-9)
            assert _tail_mean_sd(x, 0.1) == pytest.approx(ref_tail_mean_sd(x, 0.1), rel=1e-9, abs=1e-6)


def test_shared_slope_and_theil_sen_equal_the_library_fits():
    rng = np.random.default_rng(11)
    groups = [np.sort(rng.uniform(-60, 0, n)) for n in (7, 12, 5)]
    ys = [3.0 * t + c + rng.normal(0, 0.5, len(t)) for t, c in zip(groups, (10.0, -4.0, 100.0))]
    t, y, first = np.concatenate(groups), np.concatenate(ys), np.array([0, 7, 19, 24])
    ok, d, se = shared_slope(t, y, first, 0.0)
    want = ref_shared_slope([list(zip(a, b)) for a, b in zip(groups, ys)], 0.0)
    assert ok and d == pytest.approx(want[0], rel=1e-9) and se == pytest.approx(want[1], rel=1e-9)
    assert theil_sen_slope(groups[1], ys[1], np.array([0, 12])) == pytest.approx(theilslopes(ys[1], groups[1]).slope,
                                                                                  rel=1e-12)
    assert not shared_slope(t[:9], y[:9], np.array([0, 7, 9]), 0.0)[0]  # only one group of >= 3


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
        want = ref_fit_drift(legs_of(t_up, z_up, t_down, z_down, group), 2.0, phase, 0.1, PRIOR, 50_000.0)
        assert got == pytest.approx(want, rel=1e-9, abs=1e-6)
        fitted += got != PRIOR
        mine = group == group.max()
        for t, z, sign in ((t_up[mine], z_up[mine], 1), (t_down[mine], z_down[mine], -1)):
            args = (sign, got[0], 3 * got[1], 0.1, float(rng.choice([2.0, 10.0, 30.0])), 2e6)
            assert leg_envelope(t, z, *args, 3) == pytest.approx(ref_leg_envelope(t, z, *args), rel=1e-9, abs=1e-6)
    assert fitted > 40  # most windows are old enough for a fit (the rest: the prior, on both sides)


def test_a_young_window_fits_the_prior_and_three_bins_on_two_legs_fit_the_readings():
    """fit_drift needs two legs with >= 3 bins (a shared slope with an intercept per leg): with
    fewer it is the prior exactly; from then on the readings' slope (40 ppm = 40 us/s) shows."""
    rng = np.random.default_rng(4)
    young = window(rng, 39)  # 3.9 s: at most 2 bins of 2 s per leg
    assert fit_drift(*young, 2.0, 0.0, 0.1, *PRIOR, 50_000.0) == PRIOR
    drift, sd = fit_drift(*window(rng, 200), 2.0, 0.0, 0.1, *PRIOR, 50_000.0)
    assert sd < PRIOR[1] and abs(drift - 40_000.0) < 3 * sd


def _consensus_by_lexsort(t_up, z_up, t_down, z_down, drift, slack_ns, among):
    """Marzullo's point as np.lexsort of (-kinds, points) defines it (an opening before a closing)."""
    lo, hi = -(z_down + drift * t_down) - slack_ns, (z_up - drift * t_up) + slack_ns
    points = np.concatenate((lo[among], hi[among]))
    voters = int(np.count_nonzero(among))
    kinds = np.concatenate((np.ones(voters), -np.ones(voters)))
    order = np.lexsort((-kinds, points))
    theta = points[order][int(np.argmax(np.cumsum(kinds[order])))]
    return (lo <= theta) & (theta <= hi)


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
        assert np.array_equal(consensus(*args, among), _consensus_by_lexsort(*args, among))


def test_the_sort_s_shortcuts_and_the_k_least_equal_numpy_s_stable_argsort():
    """_order's shortcuts (readings by time, ages by time) and _lowest (the k least, stable) give
    np.argsort(kind="stable") exactly: sorted, reversed, tied, constant, random, -0.0 beside 0.0 and
    NaN inputs (_lowest: its first k, for every k)."""
    from obu_service.clock_envelope import _lowest

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
