"""The plain numpy definitions of ``v2i.clock.clock_envelope``'s compiled window fit (its reference).

``fit_window`` here computes what the kernel ``clock_envelope.fit_window`` computes, by the numpy
and Python expressions its docstrings state (sorts, ``np.unique``, medians and percentiles,
least squares per group), equal to rounding (tests/unit/test_clock_envelope.py). It is not used
at run time: on the windows recorded in a connected-intersection run (923 fits of 1-230
exchanges) it takes ~690 us per fit against the kernel's ~26-30 us, a quarter of the run's
~2.4 s, which is why the kernel stays (a busy 2-core machine, alternating, median of 7).
Arrays as in ``clock_envelope``: a leg is (t (n,) s, z (n,) ns, sign +1 up / -1 down).
"""

from __future__ import annotations

import math

import numpy as np

from v2i.clock.clock_envelope import NS_PER_S, QUEUED_NS


def tail_size(n: int, q: float) -> int:
    """max(1, ceil(q n)), at most n."""
    return min(n, max(1, math.ceil(q * n)))


def tail_mean_sd(r: np.ndarray, q: float) -> float:
    """Per-observation sd of the mean of the lowest fraction q of r (``clock_envelope._tail_mean_sd``)."""
    tail = np.sort(r)[:tail_size(len(r), q)]
    dev = tail - tail[-1]
    return float(np.sqrt(max(np.mean(dev**2) / q - np.mean(dev) ** 2, 0.0)))


def bin_points(t: np.ndarray, r: np.ndarray, sign: float, d: float, bin_s: float, phase_s: float,
               q: float) -> list[tuple[float, float, int]]:
    """(mean t, sign E + d t, count) of each bin of un-queued readings."""
    bins = np.floor((t + phase_s) / bin_s)
    keep = r <= r.min() + QUEUED_NS
    t, r, bins = t[keep], r[keep], bins[keep]
    values, counts = np.unique(bins, return_counts=True)
    points = [(t[bins == v].mean(), sign * np.sort(r[bins == v])[:tail_size(c, q)].mean(), c)
              for v, c in zip(values, counts)]
    return [(tb, e + d * tb, c) for tb, e, c in points]


def shared_slope(groups: list[list[tuple[float, float, float]]], min_resid: float) -> tuple[float, float] | None:
    """Weighted least squares (np.linalg.lstsq of the rows scaled by sqrt(w)) with one slope column and an
    intercept column per group, points (t, y, w): (d, se), None unless two groups have >= 3 points."""
    groups = [g for g in groups if len(g) >= 2]
    if sum(len(g) >= 3 for g in groups) < 2:
        return None
    design = np.zeros((sum(map(len, groups)), 1 + len(groups)))
    y, w, row = np.empty(len(design)), np.empty(len(design)), 0
    for k, g in enumerate(groups):
        design[row:row + len(g), 0], design[row:row + len(g), 1 + k] = [p[0] for p in g], 1.0
        y[row:row + len(g)], w[row:row + len(g)] = [p[1] for p in g], [p[2] for p in g]
        row += len(g)
    root = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(design * root[:, None], y * root, rcond=None)
    rss = float(np.sum(w * (y - design @ coef) ** 2))
    sxx = sum(np.sum(wg * (tg - np.average(tg, weights=wg)) ** 2)
              for tg, wg in ((np.array([p[0] for p in g]), np.array([p[2] for p in g], float)) for g in groups))
    return coef[0], np.sqrt(max(rss / max(1, len(y) - len(groups) - 1), min_resid**2) / sxx)


def fit_drift(legs: list[tuple[np.ndarray, np.ndarray, float]], bin_s: float, phase_s: float, q: float,
              prior: tuple[float, float], min_resid: float) -> tuple[float, float]:
    """``clock_envelope.fit_drift`` of legs [(t, z, sign)] as its docstring defines it."""
    legs = [leg for leg in legs if len(leg[0]) >= 3]
    if sum(len(np.unique(np.floor((t + phase_s) / bin_s))) >= 3 for t, _, _ in legs) < 2:
        return prior
    (d0, sd0), d = prior, prior[0]
    for _ in range(2):
        detrended = [z - s * d * t for t, z, s in legs]
        groups = [bin_points(t, r, s, d, bin_s, phase_s, q) for (t, _, s), r in zip(legs, detrended)]
        per_bin = np.mean([p[2] for g in groups for p in g])  # the mean count of a bin
        floor = max(min_resid * np.sqrt(per_bin), max(tail_mean_sd(r, q) for r in detrended))  # per reading
        slopes = [(b[1] - a[1]) / (b[0] - a[0])
                  for g in groups for i, a in enumerate(g) for b in g[i + 1:] if b[0] != a[0]]
        if slopes:  # Theil-Sen per group; the points above its line by more than 3 floor (congested) left out
            robust, cut = np.median(slopes), 3 * floor / np.sqrt(per_bin)
            groups = [g if len(g) < 4 else [p for p, e in zip(g, excess) if e <= np.percentile(excess, 25) + cut]
                      for g, (_, _, s) in zip(groups, legs) for excess in [[s * (y - robust * t) for t, y, _ in g]]]
        fit = shared_slope(groups, floor)
        if fit is None:
            return prior
        s, se = fit
        d, sd = d0 + sd0**2 / (sd0**2 + se**2) * (s - d0), (1 / sd0**2 + 1 / se**2) ** -0.5
    return d, sd


def leg_envelope(t: np.ndarray, z: np.ndarray, sign: float, drift: float, drift_bound: float, q: float,
                 horizon_s: float, margin_ns: float, min_readings: int = 3) -> tuple[float, float]:
    """``clock_envelope.leg_envelope``: (E, a) over the horizon that keeps E + drift_bound a lowest."""
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


def allowed(t_up, z_up, t_down, z_down, drift, slack_ns) -> tuple[np.ndarray, np.ndarray]:
    """The offsets theta(0) each exchange allows, [-(x_down + d t4), x_up - d t1] widened by slack (ns)."""
    return -(z_down + drift * t_down) - slack_ns, (z_up - drift * t_up) + slack_ns


def consensus(t_up, z_up, t_down, z_down, drift, slack_ns, among) -> np.ndarray:
    """Marzullo's point as np.lexsort of (-kinds, points) defines it (an opening before a closing), and the
    exchanges whose interval holds it (``clock_envelope.consensus``)."""
    lo, hi = allowed(t_up, z_up, t_down, z_down, drift, slack_ns)
    points = np.concatenate((lo[among], hi[among]))
    voters = int(np.count_nonzero(among))
    kinds = np.concatenate((np.ones(voters), -np.ones(voters)))
    order = np.lexsort((-kinds, points))
    theta = points[order][int(np.argmax(np.cumsum(kinds[order])))]
    return (lo <= theta) & (theta <= hi)


def fit_window(times: np.ndarray, segment: np.ndarray, prev_drift: float, prev_sd: float, prior_drift: float,
               prior_sd: float, bin_ns: int, q: float, max_drift: float, sigmas: float, horizon_s: float,
               threshold_ns: float, step_span: int, armed_after: int, min_resid: float) -> tuple:
    """``clock_envelope.fit_window`` (its arguments and its 11 results)."""
    newest = segment.max()
    last = int(np.flatnonzero(segment == newest)[-1])
    t_ref = times[-1, 3]
    theta_ref = ((times[last, 1] - times[last, 0]) + (times[last, 2] - times[last, 3])) // 2
    t1, t2, t3, t4 = times.T
    t_up, z_up = (t1 - t_ref) / NS_PER_S, (t2 - t1 - theta_ref).astype(float)
    t_down, z_down = (t4 - t_ref) / NS_PER_S, (t4 - t3 + theta_ref).astype(float)
    slack = sigmas * prev_sd * np.maximum(-t_up, -t_down) + 1_000.0
    current = segment == newest
    agree = consensus(t_up, z_up, t_down, z_down, prev_drift, slack, current) & current
    outside = current & ~agree
    group = np.where(outside, -1, np.searchsorted(np.unique(segment), segment))  # each segment's rank
    keep = np.flatnonzero(agree)
    contested = 2 * int(outside.sum()) >= len(keep)
    legs = [leg for g in range(group.max() + 1) for leg in ((t_up[group == g], z_up[group == g], 1.0),
                                                            (t_down[group == g], z_down[group == g], -1.0))]
    drift, sd = fit_drift(legs, bin_ns / NS_PER_S, (t_ref % bin_ns) / NS_PER_S, q, (prior_drift, prior_sd), min_resid)
    if not np.isnan(drift):
        drift = min(max(drift, -max_drift), max_drift)
    cu_t, cu_z, cd_t, cd_z = t_up[keep], z_up[keep], t_down[keep], z_down[keep]
    drift_bound = sigmas * sd
    e_up, a_up = leg_envelope(cu_t, cu_z, 1.0, drift, drift_bound, q, horizon_s, threshold_ns)
    e_down, a_down = leg_envelope(cd_t, cd_z, -1.0, drift, drift_bound, q, horizon_s, threshold_ns)
    theta_rel = 0.5 * (e_up - e_down)
    bound = 0.5 * (e_up + e_down) + drift_bound * 0.5 * (a_up + a_down)
    if contested and outside.any():  # as far as the offsets the others allow
        lo, hi = allowed(t_up[outside], z_up[outside], t_down[outside], z_down[outside], drift, slack[outside])
        bound = max(bound, np.abs(lo - theta_rel).max(), np.abs(hi - theta_rel).max())
    settled = len(keep) - step_span
    span = max(1, settled)  # the least settled detrended reading of each leg
    i_up, i_down = int(np.argmin(cu_z[:span] - drift * cu_t[:span])), int(np.argmin(cd_z[:span] + drift * cd_t[:span]))
    armed = not contested and settled >= armed_after
    return (outside, theta_ref, theta_rel, drift, sd, max(0.0, bound), cu_z[i_up] - drift * cu_t[i_up],
            times[keep[i_up], 0], cd_z[i_down] + drift * cd_t[i_down], times[keep[i_down], 3], armed)
