"""Lower-envelope statistics of one-way clock readings (compiled; see clock_sync for the model).

A one-way reading is a true delay (>= 0) plus or minus the clock offset; queueing only ever adds
delay, so the information is in the lower tail of each leg's readings (Paxson 1998; Moon et al.
1999). Readings are detrended with a drift d (ns per s): an up reading z_up = up + theta(t) has
z_up - d t = up + theta(0), a down reading z_down = down - theta(t) has z_down + d t = down -
theta(0). With sign s = +1 (up) or -1 (down): z - s d t is the detrended reading of either leg.

A vehicle refits each RSU's and each peer's window (up to a few hundred exchanges) every few
exchanges; written as numpy the fit was some 200 calls of ~1 us fixed cost each, so the
statistics are loops compiled by numba (``fusion.jit``): one kernel, ``fit_window``, per fit.
Their numpy definitions, which they equal to rounding, are in ``tests/unit/test_clock_envelope.py``.
A window's exchanges are arrays of shape (n,): ``t_up`` (s, t1 - t_ref), ``z_up`` (ns, x_up),
``t_down`` (s, t4 - t_ref), ``z_down`` (ns, x_down).
"""

from __future__ import annotations

import math

import numpy as np

from fusion.jit import F64, I64, IN_I1, IN_I2, helper, kernel

# Readings more than this above their leg's least (detrended) reading are buffered or queued
# far beyond any drift trend (500 ppm x 60 s = 30 ms): never part of a lower envelope.
QUEUED_NS = 200_000_000.0
NS_PER_S = 1_000_000_000


# --- one leg ---------------------------------------------------------------------------------

@helper
def _tail_size(n: int, q: float) -> int:
    """max(1, ceil(q n)), at most n: how many readings make the lower tail of n."""
    return min(n, max(1, math.ceil(q * n)))


@helper
def _order(x: np.ndarray) -> np.ndarray:
    """np.argsort(x, kind="stable") of a (n,) float64 array without NaN: a bottom-up merge sort
    (numba's own sorts take about a second each to compile)."""
    n = len(x)
    a, b = np.arange(n), np.empty(n, np.int64)
    width = 1
    while width < n:
        for lo in range(0, n, 2 * width):
            mid, hi = min(lo + width, n), min(lo + 2 * width, n)
            i, j = lo, mid
            for k in range(lo, hi):
                if i < mid and (j >= hi or x[a[i]] <= x[a[j]]):  # equal: the left run's first
                    b[k], i = a[i], i + 1
                else:
                    b[k], j = a[j], j + 1
        a, b = b, a
        width *= 2
    return a


@helper
def _sorted(x: np.ndarray) -> np.ndarray:
    return x[_order(x)]


@helper
def _quantile(ascending: np.ndarray, p: float) -> float:
    """The p-quantile of a sorted (n,) array, n >= 1, by linear interpolation (numpy's default
    method): v = p (n - 1), s[floor v] + (s[floor v + 1] - s[floor v]) (v - floor v). (np.median and
    np.percentile would take seconds more to compile.)"""
    v = p * (len(ascending) - 1)
    i = int(v)
    a, b = ascending[i], ascending[min(i + 1, len(ascending) - 1)]
    return a + (b - a) * (v - i)


@helper
def _unqueued(r: np.ndarray) -> np.ndarray:
    """(n,) True where a detrended reading is within QUEUED_NS of the leg's least one."""
    return r <= r.min() + QUEUED_NS


@helper
def _tail_mean(r: np.ndarray, t_s: np.ndarray, q: float) -> tuple[float, float]:
    """(E, a): the mean of the lowest fraction q of the readings r, and their mean age -t (s, >= 0)."""
    k = _tail_size(len(r), q)
    low = _order(r)[:k]
    return r[low].sum() / k, max(0.0, -(t_s[low].sum() / k))


@helper
def _tail_mean_sd(r: np.ndarray, q: float) -> float:
    """Per-observation sd of the mean of the lowest fraction q of r (from its influence function):

    L = (1/q) int_0^q Q(p) dp,  IF(x) = min(x - Q_q, 0) / q + const, so
    var = E[(x - Q_q)^2 | tail] / q - (mean_tail - Q_q)^2.
    """
    k = _tail_size(len(r), q)
    tail = _sorted(r)[:k]  # the k lowest, ascending
    dev = tail - tail[k - 1]  # tail[-1] ~ Q_q
    return math.sqrt(max((dev * dev).sum() / k / q - (dev.sum() / k) ** 2, 0.0))


@helper
def leg_envelope(t_s: np.ndarray, z_ns: np.ndarray, sign: int, drift: float, drift_bound: float, q: float,
                 horizon_s: float, margin_ns: float, min_readings: int) -> tuple[float, float]:
    """(E, a): the lower-tail mean of a leg (and its mean age) over the horizon that keeps its
    bound E + drift_bound * a low.

    Readings more than QUEUED_NS above the leg's least one (buffered) are never part of its lower
    tail. Starts from the readings of the last horizon_s (at least the newest min_readings) and
    doubles the horizon while that bounds the leg better by more than margin_ns: a drift error of
    at most drift_bound (ns/s) moves a reading of age a by drift_bound a, so an older, un-queued
    envelope is worth more than a recent one whose every reading was buffered.
    """
    r = z_ns - sign * drift * t_s
    usable = np.arange(len(r))[_unqueued(r)]
    order = usable[_order(-t_s[usable])]  # un-queued readings, newest first
    ages = -t_s[order]  # ascending
    best_e, best_a, best_bound, h = 0.0, 0.0, np.inf, horizon_s
    while True:
        within = 0  # readings no older than h
        while within < len(ages) and ages[within] <= h:
            within += 1
        count = max(min(min_readings, len(order)), within)
        e, a = _tail_mean(r[order[:count]], t_s[order[:count]], q)
        bound = e + drift_bound * a
        if best_bound == np.inf or bound < best_bound - margin_ns:
            best_e, best_a, best_bound = e, a, bound
        if h >= ages[-1]:
            return best_e, best_a
        h *= 2.0


# --- the drift ---------------------------------------------------------------------------------

@helper
def _legs(t_up, z_up, t_down, z_down, group):
    """The readings of each leg with >= 3, leg by leg: segment g's up leg, then its down leg
    (exchanges of group -1 are left out). (t, z) (m,), sign (L,), first (L + 1,): leg l's readings
    are [first[l], first[l + 1]). (Loops: numpy's functions here took seconds to compile.)"""
    n_groups = 0
    for g in group:
        n_groups = max(n_groups, g + 1)
    counts = np.zeros(n_groups, np.int64)
    for g in group:
        if g >= 0:
            counts[g] += 1
    slot = np.full(n_groups, -1, np.int64)  # each segment's up leg, if it has >= 3 readings
    n_legs = 0
    for g in range(n_groups):
        if counts[g] >= 3:
            slot[g], n_legs = n_legs, n_legs + 2
    first, sign = np.zeros(n_legs + 1, np.int64), np.empty(n_legs)
    for g in range(n_groups):
        if slot[g] >= 0:
            leg = slot[g]
            first[leg + 1], first[leg + 2] = first[leg] + counts[g], first[leg] + 2 * counts[g]
            sign[leg], sign[leg + 1] = 1.0, -1.0
    t, z, fill = np.empty(first[-1]), np.empty(first[-1]), first[:-1].copy()
    for i in range(len(group)):
        leg = slot[group[i]] if group[i] >= 0 else -1
        if leg >= 0:
            t[fill[leg]], z[fill[leg]] = t_up[i], z_up[i]
            t[fill[leg + 1]], z[fill[leg + 1]] = t_down[i], z_down[i]
            fill[leg] += 1
            fill[leg + 1] += 1
    return t, z, sign, first


@helper
def _bin_layout(bins: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order, edges): the readings by bin (stable), bin j's being order[edges[j]:edges[j + 1]]."""
    order = _order(bins)
    edges = np.empty(len(bins) + 1, np.int64)
    m = 1
    edges[0] = 0
    for i in range(1, len(order)):
        if bins[order[i]] != bins[order[i - 1]]:
            edges[m], m = i, m + 1
    edges[m] = len(order)
    return order, edges[:m + 1]


@helper
def _bin_envelopes(t: np.ndarray, order: np.ndarray, edges: np.ndarray, r: np.ndarray, sign: float, drift: float,
                   q: float, out_t: np.ndarray, out_y: np.ndarray) -> int:
    """Per bin of a leg, (mean t, sign * (E + sign d t)): points on a line of slope d, written to
    out_t[:m], out_y[:m]; returns m.

    (order, edges): the leg's readings by bin (``_bin_layout`` of floor((t + phase_s) / bin_s):
    edges at t = k bin_s - phase_s, fixed in absolute time as the reference time moves); ``r``: the
    readings detrended with ``drift``; E: the mean of the lowest fraction q of r in the bin.
    Buffered readings (QUEUED_NS) say nothing about the envelope's slope and are left out; bins
    holding fewer than half the median count (half-filled bins at the window edges) too: their
    lower tail is a weaker lower bound.
    """
    unqueued = _unqueued(r)
    n_bins = len(edges) - 1
    counts, t_sum = np.zeros(n_bins, np.int64), np.zeros(n_bins)
    r_bin = np.empty(len(r))  # the un-queued readings of each bin, bin after bin
    for b in range(n_bins):
        for i in order[edges[b]:edges[b + 1]]:
            if unqueued[i]:
                r_bin[edges[b] + counts[b]] = r[i]
                t_sum[b] += t[i]
                counts[b] += 1
    least = 0.5 * _quantile(_sorted(counts[counts > 0].astype(np.float64)), 0.5)  # half the median count
    m = 0
    for b in range(n_bins):
        c = counts[b]
        if c == 0 or c < least:
            continue
        k = _tail_size(c, q)
        t_bin, e_bin = t_sum[b] / c, _sorted(r_bin[edges[b]:edges[b] + c])[:k].sum() / k
        out_t[m], out_y[m] = t_bin, sign * e_bin + drift * t_bin
        m += 1
    return m


@helper
def theil_sen_slope(t: np.ndarray, y: np.ndarray, first: np.ndarray) -> float:
    """Median of the pairwise slopes (y_j - y_i) / (t_j - t_i) within each group (Theil 1950, Sen
    1968, grouped so that each group keeps its own intercept; group g is [first[g], first[g + 1]));
    NaN without a pair."""
    pairs = 0
    for g in range(len(first) - 1):
        m = first[g + 1] - first[g]
        pairs += m * (m - 1) // 2
    slopes, k = np.empty(pairs), 0
    for g in range(len(first) - 1):
        for i in range(first[g], first[g + 1]):
            for j in range(i + 1, first[g + 1]):
                if t[j] != t[i]:
                    slopes[k] = (y[j] - y[i]) / (t[j] - t[i])
                    k += 1
    return _quantile(_sorted(slopes[:k]), 0.5) if k else np.nan  # the median


@helper
def _below_line(t, y, first, sign, d, limit):
    """The points of each group whose envelope is not congested: sign (y - d t) <= c + limit, c the
    lower quartile of sign (y - d t) over the group (a congested bin lies above the envelope line);
    groups of fewer than 4 are kept whole. Returns (t, y, first) of the points kept."""
    keep = np.ones(len(t), np.bool_)
    for g in range(len(first) - 1):
        a, b = first[g], first[g + 1]
        if b - a >= 4:
            excess = sign[g] * (y[a:b] - d * t[a:b])
            keep[a:b] = excess <= _quantile(_sorted(excess), 0.25) + limit
    kept_first = np.zeros(len(first), np.int64)
    for g in range(len(first) - 1):
        kept_first[g + 1] = kept_first[g] + keep[first[g]:first[g + 1]].sum()
    return t[keep], y[keep], kept_first


@helper
def shared_slope(t: np.ndarray, y: np.ndarray, first: np.ndarray, min_resid: float) -> tuple[bool, float, float]:
    """(ok, d, se): the least-squares slope shared by point groups (group g: [first[g], first[g + 1])),
    each with its own intercept, and its std error.

    d = sum_g sum_i (t_i - tbar_g)(y_i - ybar_g) / Sxx,  Sxx = sum_g sum_i (t_i - tbar_g)^2,
    se = sqrt(s^2 / Sxx),  s^2 = RSS / (m - G - 1) floored at min_resid^2 (m points, G groups of
    >= 2 points); not ok unless two groups have >= 3 points spread in t.
    """
    tc, yc = np.empty(len(t)), np.empty(len(t))
    groups, points, wide = 0, 0, 0
    for g in range(len(first) - 1):
        a, b = first[g], first[g + 1]
        if b - a < 2:
            tc[a:b], yc[a:b] = 0.0, 0.0  # a lone point adds nothing to the sums
            continue
        tc[a:b], yc[a:b] = t[a:b] - t[a:b].sum() / (b - a), y[a:b] - y[a:b].sum() / (b - a)
        groups, points, wide = groups + 1, points + b - a, wide + (b - a >= 3)
    sxx = (tc * tc).sum()
    if wide < 2 or sxx <= 0.0:
        return False, 0.0, 0.0
    d = (tc * yc).sum() / sxx
    resid = yc - d * tc
    dof = max(1, points - groups - 1)
    return True, d, math.sqrt(max((resid * resid).sum() / dof, min_resid**2) / sxx)


@helper
def fit_drift(t_up: np.ndarray, z_up: np.ndarray, t_down: np.ndarray, z_down: np.ndarray, group: np.ndarray,
              bin_s: float, phase_s: float, q: float, prior_drift: float, prior_sd: float,
              min_resid: float) -> tuple[float, float]:
    """(drift, sd) in ns per s of the lower envelopes of both legs of every clock segment, shrunk
    to a prior; ``group`` (n,): each exchange's segment 0, 1, ... (-1: left out).

    Per sub-window (bin of bin_s seconds, edges at k bin_s - phase_s) and leg, the lower-tail
    mean of the readings detrended with the current drift d is the envelope at the bin's mean
    time; the envelopes (signed so that every leg rises with slope d) get one shared least-squares
    slope s with an intercept per leg and clock segment (a step moves the intercepts, not the
    rate: shared_slope, std error se from the scatter of the bins, but never below the expected
    scatter _tail_mean_sd / sqrt(samples per bin), so that a few bins lying on a line by chance do
    not fake certainty). Bins whose envelope lies above the grouped Theil-Sen line by more than
    3 such sd (a leg congested or buffered for a whole bin) are left out. With the prior
    N(d0, sd0^2), the Gaussian posterior is
      d = d0 + w (s - d0),  w = sd0^2 / (sd0^2 + se^2),  sd = (1 / sd0^2 + 1 / se^2)^(-1/2).
    Two passes: the second detrends with the first's drift. Legs of fewer than 3 readings are
    left out; without two legs of >= 3 bins (a young window) the fit is the prior.
    """
    t, z, sign, first = _legs(t_up, z_up, t_down, z_down, group)
    bins = np.floor((t + phase_s) / bin_s)  # the drift moves no reading across bins
    layouts = [_bin_layout(bins[first[g]:first[g + 1]]) for g in range(len(sign))]
    wide = 0
    for _, edges in layouts:
        wide += len(edges) - 1 >= 3
    if wide < 2:  # (leaving out queued readings or congested bins never adds a bin)
        return prior_drift, prior_sd
    d, sd = prior_drift, prior_sd
    pt, py, pfirst = np.empty(len(t)), np.empty(len(t)), np.zeros(len(first), np.int64)
    for _ in range(2):
        noise = 0.0  # the largest per-reading sd of a leg's lower-tail mean
        for g in range(len(sign)):
            a, b = first[g], first[g + 1]
            r = z[a:b] - sign[g] * d * t[a:b]
            noise = max(noise, _tail_mean_sd(r, q))
            order, edges = layouts[g]
            m = _bin_envelopes(t[a:b], order, edges, r, sign[g], d, q, pt[pfirst[g]:], py[pfirst[g]:])
            pfirst[g + 1] = pfirst[g] + m
        # a bin envelope scatters at least by the lower-tail-mean noise of its samples
        floor = max(min_resid, noise / math.sqrt(max(1.0, len(t) / max(pfirst[-1], 1))))
        et, ey, efirst = pt[:pfirst[-1]], py[:pfirst[-1]], pfirst
        robust = theil_sen_slope(et, ey, efirst)
        if not np.isnan(robust):
            et, ey, efirst = _below_line(et, ey, efirst, sign, robust, 3.0 * floor)
        ok, s, se = shared_slope(et, ey, efirst, floor)
        if not ok:
            return prior_drift, prior_sd
        d = prior_drift + prior_sd**2 / (prior_sd**2 + se**2) * (s - prior_drift)
        sd = (1.0 / prior_sd**2 + 1.0 / se**2) ** -0.5
    return d, sd


# --- the exchanges that agree --------------------------------------------------------------------

@helper
def consensus(t_up: np.ndarray, z_up: np.ndarray, t_down: np.ndarray, z_down: np.ndarray, drift: float,
              slack_ns: np.ndarray, among: np.ndarray) -> np.ndarray:
    """Which exchanges agree on the offset most of them allow (Marzullo 1984), bool shape (n,).

    Only those in ``among`` (bool (n,)) vote. Exchange i allows theta(0) in
    [-(x_down + d t4), x_up - d t1] (both delays >= 0), widened by slack_ns[i] for the drift error;
    genuine exchanges all contain the true offset, so the point covered by the most intervals (the
    first such, an opening before a closing at the same value) is kept, and an exchange whose
    interval misses it (a forged or stepped reply among agreeing ones) is not.
    """
    lo = -(z_down + drift * t_down) - slack_ns
    hi = (z_up - drift * t_up) + slack_ns
    points = np.concatenate((lo[among], hi[among]))  # the voters' openings, then their closings
    voters = len(points) // 2
    order = _order(points)  # stable: at equal values openings come first
    covered, most, theta = 0, -1, 0.0
    for i in order:
        covered += 1 if i < voters else -1
        if covered > most:
            most, theta = covered, points[i]
    return (lo <= theta) & (theta <= hi)


@helper
def _disputed_ns(lo: np.ndarray, hi: np.ndarray, theta_ns: float) -> float:
    """How far from theta_ns the offsets [lo, hi] allowed by some exchanges reach (ns, the far edge of
    the farthest): what the bound must cover when those may be the genuine ones."""
    return max(np.abs(lo - theta_ns).max(), np.abs(hi - theta_ns).max()) if len(lo) else 0.0


# --- a window's fit ------------------------------------------------------------------------------

@kernel(IN_I2, IN_I1, F64, F64, F64, F64, I64, F64, F64, F64, F64, F64, I64, I64, F64)
def fit_window(times: np.ndarray, segment: np.ndarray, prev_drift: float, prev_sd: float, prior_drift: float,
               prior_sd: float, bin_ns: int, q: float, max_drift: float, sigmas: float, horizon_s: float,
               threshold_ns: float, step_span: int, armed_after: int, min_resid: float):
    """The fit of a window of n exchanges (the model and its parameters: clock_sync.ClockSync).

    times (n, 4) int64 [t1, t2, t3, t4] ns by t4; segment (n,) int64 each exchange's clock
    segment; (prev_drift, prev_sd) the last fit's drift (ns/s; it widens the consensus).
    Returns (outside, theta_ref, theta_rel, drift, sd, bound, least_up, t1 of it, least_down,
    t4 of it, armed): outside (n,) the exchanges of the current segment the consensus left out;
    readings relative to theta_ref, the offset of the newest exchange of the current segment
    (the newest segment left), at t_ref = the newest t4.
    """
    n = len(segment)
    current = segment == segment.max()
    last = np.flatnonzero(current)[-1]
    t1, t2, t3, t4 = times[:, 0], times[:, 1], times[:, 2], times[:, 3]
    t_ref = t4[n - 1]
    theta_ref = ((t2[last] - t1[last]) + (t3[last] - t4[last])) // 2
    t_up, z_up = (t1 - t_ref) / NS_PER_S, (t2 - t1 - theta_ref).astype(np.float64)  # up + theta - theta_ref
    t_down, z_down = (t4 - t_ref) / NS_PER_S, (t4 - t3 + theta_ref).astype(np.float64)  # down - (theta - theta_ref)
    # what a drift error of sigmas sd (of the last fit) does over each exchange's age
    slack = sigmas * prev_sd * np.maximum(-t_up, -t_down) + 1_000.0
    agree = current & consensus(t_up, z_up, t_down, z_down, prev_drift, slack, current)
    outside = current & ~agree
    present = np.zeros(segment.max() + 1, np.int64)
    present[segment] = 1
    group = (np.cumsum(present) - 1)[segment]  # each exchange's segment by rank among those present
    group[outside] = -1
    drift, sd = fit_drift(t_up, z_up, t_down, z_down, group, bin_ns / NS_PER_S, (t_ref % bin_ns) / NS_PER_S, q,
                          prior_drift, prior_sd, min_resid)
    if not np.isnan(drift):
        drift = min(max(drift, -max_drift), max_drift)
    # the offset at t_ref from the lower envelopes of the current segment's agreeing exchanges
    keep = np.flatnonzero(agree)
    cu_t, cu_z, cd_t, cd_z = t_up[keep], z_up[keep], t_down[keep], z_down[keep]
    drift_bound = sigmas * sd
    e_up, a_up = leg_envelope(cu_t, cu_z, 1, drift, drift_bound, q, horizon_s, threshold_ns, 3)
    e_down, a_down = leg_envelope(cd_t, cd_z, -1, drift, drift_bound, q, horizon_s, threshold_ns, 3)
    theta_rel = 0.5 * (e_up - e_down)
    bound = 0.5 * (e_up + e_down) + drift_bound * 0.5 * (a_up + a_down)
    contested = 2 * outside.sum() >= len(keep)  # no clear majority: the others may be right
    if contested:
        lo = -(z_down[outside] + drift * t_down[outside]) - slack[outside]
        hi = (z_up[outside] - drift * t_up[outside]) + slack[outside]
        bound = max(bound, _disputed_ns(lo, hi, theta_rel))
    settled = len(keep) - step_span  # the newest step_span are on probation
    r_up, r_down = cu_z - drift * cu_t, cd_z + drift * cd_t  # the least settled detrended reading of each leg
    i_up, i_down = np.argmin(r_up[:max(1, settled)]), np.argmin(r_down[:max(1, settled)])
    armed = not contested and settled >= armed_after
    return (outside, theta_ref, theta_rel, drift, sd, max(0.0, bound), r_up[i_up], t1[keep[i_up]], r_down[i_down],
            t4[keep[i_down]], armed)
