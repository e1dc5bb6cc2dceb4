"""Lower-envelope statistics of one-way clock readings (compiled; see clock_sync for the model).

A one-way reading is a true delay (>= 0) plus or minus the clock offset; queueing only ever adds
delay, so the information is in the lower tail of each leg's readings (Paxson 1998; Moon et al.
1999). Readings are detrended with a drift d (ns per s): an up reading z_up = up + theta(t) has
z_up - d t = up + theta(0), a down reading z_down = down - theta(t) has z_down + d t = down -
theta(0). With sign s = +1 (up) or -1 (down): z - s d t is the detrended reading of either leg.

A vehicle refits each RSU's and each peer's window (up to a few hundred exchanges) every few
exchanges; written as numpy the fit was some 200 calls of ~1 us fixed cost each, so the
statistics are loops compiled by numba (``v2i.core.jit``): one kernel, ``fit_window``, per fit
(loops, not array expressions or numpy's sorts and quantiles: each of those adds ~0.1-1 s to the
kernel's compile). Their numpy definitions, which they equal to rounding
(tests/unit/test_clock_envelope.py), are ``v2i.clock.envelope_reference``: ~690 us per fit
against the kernel's ~26-30 us on the fits of a connected-intersection run.
A window's exchanges are arrays of shape (n,): ``t_up`` (s, t1 - t_ref), ``z_up`` (ns, x_up),
``t_down`` (s, t4 - t_ref), ``z_down`` (ns, x_down).
"""

from __future__ import annotations

import math

import numpy as np

from v2i.core.jit import F64, I64, IN_I1, IN_I2, helper, kernel

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
    """np.argsort(x, kind="stable") of a (n,) float64 array without NaN: a bottom-up merge sort, after
    an O(n) look for the usual orders of a window's readings (by time: non-decreasing, its identity;
    strictly decreasing, ages of readings by time: the reverse)."""
    n = len(x)
    rising, falling = True, True
    for i in range(1, n):
        rising = rising and x[i] >= x[i - 1]  # (False at a NaN: the merge sort then orders as before)
        falling = falling and x[i] < x[i - 1]
        if not (rising or falling):
            break
    if rising:
        return np.arange(n)
    if falling:
        return np.arange(n - 1, -1, -1)
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
def _lowest(x: np.ndarray, k: int) -> np.ndarray:
    """_order(x)[:k], 1 <= k <= n, of a (n,) float64 array: the k least by (value, index), kept in
    order in a buffer (an element enters only below the buffer's last, after its equals: stable),
    without sorting the other n - k. A NaN in x: _order's own answer."""
    n = len(x)
    low = np.empty(k, np.int64)
    m = 0
    for i in range(n):
        v = x[i]
        if v != v:  # NaN
            return _order(x)[:k]
        if m == k and not v < x[low[k - 1]]:
            continue
        j = m if m < k else k - 1  # the slot freed (or the last one dropped)
        while j > 0 and v < x[low[j - 1]]:
            low[j] = low[j - 1]
            j -= 1
        low[j] = i
        m = min(m + 1, k)
    return low


@helper
def _quantile(x: np.ndarray, p: float) -> float:
    """The p-quantile of a (n,) array, n >= 1, by linear interpolation (numpy's default method):
    s sorted, v = p (n - 1), s[floor v] + (s[floor v + 1] - s[floor v]) (v - floor v)."""
    order = _order(x)
    v = p * (len(x) - 1)
    i = int(v)
    a, b = x[order[i]], x[order[min(i + 1, len(x) - 1)]]
    return a + (b - a) * (v - i)


@helper
def _detrended(t_s: np.ndarray, z_ns: np.ndarray, slope: float) -> np.ndarray:
    """z - slope t, shape (n,): a leg's readings detrended (slope = sign d)."""
    r = np.empty(len(z_ns))
    for i in range(len(z_ns)):
        r[i] = z_ns[i] - slope * t_s[i]
    return r


@helper
def _tail_mean(r: np.ndarray, t_s: np.ndarray, rows: np.ndarray, q: float) -> tuple[float, float]:
    """(E, a): the mean of the lowest fraction q of the readings r[rows], and their mean age -t (s, >= 0)."""
    k = _tail_size(len(rows), q)
    sub = np.empty(len(rows))
    for j in range(len(rows)):
        sub[j] = r[rows[j]]
    low = _lowest(sub, k)
    e, t = 0.0, 0.0
    for j in range(k):
        e += sub[low[j]]
        t += t_s[rows[low[j]]]
    return e / k, max(0.0, -(t / k))


@helper
def _tail_mean_sd(r: np.ndarray, q: float) -> float:
    """Per-observation sd of the mean of the lowest fraction q of r (from its influence function):

    L = (1/q) int_0^q Q(p) dp,  IF(x) = min(x - Q_q, 0) / q + const, so
    var = E[(x - Q_q)^2 | tail] / q - (mean_tail - Q_q)^2.
    """
    k = _tail_size(len(r), q)
    low = _lowest(r, k)
    top = r[low[k - 1]]  # ~ Q_q
    s1, s2 = 0.0, 0.0
    for j in range(k):
        dev = r[low[j]] - top
        s1 += dev
        s2 += dev * dev
    return math.sqrt(max(s2 / k / q - (s1 / k) ** 2, 0.0))


@helper
def leg_envelope(t_s: np.ndarray, z_ns: np.ndarray, sign: float, drift: float, drift_bound: float, q: float,
                 horizon_s: float, margin_ns: float, min_readings: int) -> tuple[float, float]:
    """(E, a): the lower-tail mean of a leg (and its mean age) over the horizon that keeps its
    bound E + drift_bound * a low.

    Readings more than QUEUED_NS above the leg's least one (buffered) are never part of its lower
    tail. Starts from the readings of the last horizon_s (at least the newest min_readings) and
    doubles the horizon while that bounds the leg better by more than margin_ns: a drift error of
    at most drift_bound (ns/s) moves a reading of age a by drift_bound a, so an older, un-queued
    envelope is worth more than a recent one whose every reading was buffered.
    """
    r = _detrended(t_s, z_ns, sign * drift)
    limit = r.min() + QUEUED_NS
    usable, n = np.empty(len(r), np.int64), 0
    for i in range(len(r)):
        if r[i] <= limit:
            usable[n], n = i, n + 1
    ages = np.empty(n)
    for j in range(n):
        ages[j] = -t_s[usable[j]]
    by_age = _order(ages)
    order = np.empty(n, np.int64)  # un-queued readings, newest first
    for j in range(n):
        order[j] = usable[by_age[j]]
    best_e, best_a, best_bound, h = 0.0, 0.0, np.inf, horizon_s
    oldest = ages[by_age[n - 1]]
    while True:
        within = 0  # readings no older than h
        while within < n and ages[by_age[within]] <= h:
            within += 1
        e, a = _tail_mean(r, t_s, order[:max(min(min_readings, n), within)], q)
        bound = e + drift_bound * a
        if best_bound == np.inf or bound < best_bound - margin_ns:
            best_e, best_a, best_bound = e, a, bound
        if h >= oldest:
            return best_e, best_a
        h *= 2.0


# --- the drift ---------------------------------------------------------------------------------

@helper
def _legs(t_up, z_up, t_down, z_down, group):
    """The readings of each leg with >= 3, leg by leg: segment g's up leg, then its down leg
    (exchanges of group -1 are left out). (t, z) (m,), sign (L,), first (L + 1,): leg l's readings
    are [first[l], first[l + 1])."""
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
                   q: float, out_t: np.ndarray, out_y: np.ndarray, out_w: np.ndarray) -> int:
    """Per bin of a leg, (mean t, sign * (E + sign d t), c): points on a line of slope d and their
    weights, written to out_t[:m], out_y[:m], out_w[:m]; returns m.

    (order, edges): the leg's readings by bin (``_bin_layout`` of floor((t + phase_s) / bin_s):
    edges at t = k bin_s - phase_s, fixed in absolute time as the reference time moves); ``r``: the
    readings detrended with ``drift``; E: the mean of the lowest fraction q of r in the bin, c its
    count of readings. Buffered readings (QUEUED_NS) say nothing about the envelope's slope and are
    left out. Every bin with a reading is kept, the half-filled ones at the window's edges too (they
    hold the oldest and the newest readings, the slope's leverage): the lower-tail mean of c
    readings of per-reading sd sigma has variance ~ sigma^2 / c, so a bin's weight is c.
    """
    limit = r.min() + QUEUED_NS
    n_bins = len(edges) - 1
    rows = np.empty(len(r), np.int64)  # the un-queued readings of a bin
    m = 0
    for b in range(n_bins):
        c, t_sum = 0, 0.0
        for i in order[edges[b]:edges[b + 1]]:
            if r[i] <= limit:
                rows[c], t_sum, c = i, t_sum + t[i], c + 1
        if c == 0:
            continue
        t_bin = t_sum / c
        e_bin, _ = _tail_mean(r, t, rows[:c], q)
        out_t[m], out_y[m], out_w[m] = t_bin, sign * e_bin + drift * t_bin, c
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
    return _quantile(slopes[:k], 0.5) if k else np.nan  # the median


@helper
def _below_line(t, y, w, first, sign, d, limit):
    """The points of each group whose envelope is not congested: sign (y - d t) <= c + limit, c the
    lower quartile of sign (y - d t) over the group (a congested bin lies above the envelope line);
    groups of fewer than 4 are kept whole. Returns (t, y, w, first) of the points kept."""
    out_t, out_y, out_w = np.empty(len(t)), np.empty(len(t)), np.empty(len(t))
    out_first = np.zeros(len(first), np.int64)
    m = 0
    for g in range(len(first) - 1):
        a, b = first[g], first[g + 1]
        excess = np.empty(b - a)
        for i in range(a, b):
            excess[i - a] = sign[g] * (y[i] - d * t[i])
        cut = _quantile(excess, 0.25) + limit if b - a >= 4 else np.inf
        for i in range(a, b):
            if excess[i - a] <= cut:
                out_t[m], out_y[m], out_w[m], m = t[i], y[i], w[i], m + 1
        out_first[g + 1] = m
    return out_t[:m], out_y[:m], out_w[:m], out_first


@helper
def _wmean(x: np.ndarray, w: np.ndarray, a: int, b: int) -> float:
    """sum w x / sum w over [a, b)."""
    s, sw = 0.0, 0.0
    for i in range(a, b):
        s += w[i] * x[i]
        sw += w[i]
    return s / sw


@helper
def shared_slope(t: np.ndarray, y: np.ndarray, w: np.ndarray, first: np.ndarray,
                 min_resid: float) -> tuple[bool, float, float]:
    """(ok, d, se): the weighted least-squares slope shared by point groups (group g: [first[g],
    first[g + 1])), each with its own intercept, and its std error; point i has variance s^2 / w_i.

    d = sum_g sum_i w_i (t_i - tbar_g)(y_i - ybar_g) / Sxx,  Sxx = sum_g sum_i w_i (t_i - tbar_g)^2,
    tbar_g, ybar_g the weighted means of group g, se = sqrt(s^2 / Sxx),
    s^2 = sum w_i (y_i - ybar_g - d (t_i - tbar_g))^2 / (m - G - 1) floored at min_resid^2 (m points,
    G groups of >= 2 points); not ok unless two groups have >= 3 points spread in t.
    """
    groups, points, wide, sxx, sxy = 0, 0, 0, 0.0, 0.0
    for g in range(len(first) - 1):
        a, b = first[g], first[g + 1]
        if b - a < 2:
            continue
        t_bar, y_bar = _wmean(t, w, a, b), _wmean(y, w, a, b)
        for i in range(a, b):
            sxx += w[i] * (t[i] - t_bar) ** 2
            sxy += w[i] * (t[i] - t_bar) * (y[i] - y_bar)
        groups, points, wide = groups + 1, points + b - a, wide + (b - a >= 3)
    if wide < 2 or sxx <= 0.0:
        return False, 0.0, 0.0
    d, rss = sxy / sxx, 0.0
    for g in range(len(first) - 1):
        a, b = first[g], first[g + 1]
        if b - a >= 2:
            t_bar, y_bar = _wmean(t, w, a, b), _wmean(y, w, a, b)
            for i in range(a, b):
                rss += w[i] * ((y[i] - y_bar) - d * (t[i] - t_bar)) ** 2
    return True, d, math.sqrt(max(rss / max(1, points - groups - 1), min_resid**2) / sxx)


@helper
def fit_drift(t_up: np.ndarray, z_up: np.ndarray, t_down: np.ndarray, z_down: np.ndarray, group: np.ndarray,
              bin_s: float, phase_s: float, q: float, prior_drift: float, prior_sd: float,
              min_resid: float) -> tuple[float, float]:
    """(drift, sd) in ns per s of the lower envelopes of both legs of every clock segment, shrunk
    to a prior; ``group`` (n,): each exchange's segment 0, 1, ... (-1: left out).

    Per sub-window (bin of bin_s seconds, edges at k bin_s - phase_s) and leg, the lower-tail
    mean of the readings detrended with the current drift d is the envelope at the bin's mean
    time; the envelopes (signed so that every leg rises with slope d) get one shared weighted
    least-squares slope s with an intercept per leg and clock segment (a step moves the
    intercepts, not the rate: shared_slope). A bin of c un-queued readings has variance
    sigma^2 / c (sigma: the per-reading sd of a lower-tail mean), so its weight is c and the
    half-filled bins at the window's edges count for what they hold instead of being dropped:
    they carry the oldest and newest readings, the slope's leverage, which is what a young
    window lacks (lte-v2x, -85 ppm, 60 seeds, fits 15 s into the run: rms drift error 43.5 ->
    36.8 ppm). The std error se comes from the weighted scatter of the bins, per reading
    s^2 = sum c_b res_b^2 / (m - G - 1), but never below the expected scatter
    sigma^2 = _tail_mean_sd^2 (nor min_resid^2 per bin of the mean count), so that a few bins
    lying on a line by chance do not fake certainty. Bins whose envelope lies above the grouped
    Theil-Sen line by more than 3 sigma / sqrt(mean count) (a leg congested or buffered for a
    whole bin) are left out. With the prior N(d0, sd0^2), the Gaussian posterior is
      d = d0 + w (s - d0),  w = sd0^2 / (sd0^2 + se^2),  sd = (1 / sd0^2 + 1 / se^2)^(-1/2).
    Two passes: the second detrends with the first's drift. Legs of fewer than 3 readings are
    left out; without two legs of >= 3 bins (a young window) the fit is the prior.
    """
    t, z, sign, first = _legs(t_up, z_up, t_down, z_down, group)
    bins = np.empty(len(t))
    for i in range(len(t)):
        bins[i] = math.floor((t[i] + phase_s) / bin_s)  # the drift moves no reading across bins
    layouts = [_bin_layout(bins[first[g]:first[g + 1]]) for g in range(len(sign))]
    wide = 0
    for _, edges in layouts:
        wide += len(edges) - 1 >= 3
    if wide < 2:  # (leaving out queued readings or congested bins never adds a bin)
        return prior_drift, prior_sd
    d, sd = prior_drift, prior_sd
    pt, py, pw = np.empty(len(t)), np.empty(len(t)), np.empty(len(t))
    pfirst = np.zeros(len(first), np.int64)
    for _ in range(2):
        noise = 0.0  # the largest per-reading sd of a leg's lower-tail mean
        for g in range(len(sign)):
            a, b = first[g], first[g + 1]
            r = _detrended(t[a:b], z[a:b], sign[g] * d)
            noise = max(noise, _tail_mean_sd(r, q))
            order, edges = layouts[g]
            m = _bin_envelopes(t[a:b], order, edges, r, sign[g], d, q, pt[pfirst[g]:], py[pfirst[g]:], pw[pfirst[g]:])
            pfirst[g + 1] = pfirst[g] + m
        # per reading, a bin envelope scatters at least by the lower-tail-mean noise (sigma), and by
        # min_resid at a bin of the mean count c_mean = sum c / m
        count = 0.0
        for i in range(pfirst[-1]):
            count += pw[i]
        per_bin = count / pfirst[-1]  # c_mean (each leg has a bin: its least reading is never queued)
        floor = max(min_resid * math.sqrt(per_bin), noise)
        et, ey, ew, efirst = pt[:pfirst[-1]], py[:pfirst[-1]], pw[:pfirst[-1]], pfirst
        robust = theil_sen_slope(et, ey, efirst)
        if not np.isnan(robust):
            et, ey, ew, efirst = _below_line(et, ey, ew, efirst, sign, robust, 3.0 * floor / math.sqrt(per_bin))
        ok, s, se = shared_slope(et, ey, ew, efirst, floor)
        if not ok:
            return prior_drift, prior_sd
        d = prior_drift + prior_sd**2 / (prior_sd**2 + se**2) * (s - prior_drift)
        sd = (1.0 / prior_sd**2 + 1.0 / se**2) ** -0.5
    return d, sd


# --- the exchanges that agree --------------------------------------------------------------------

@helper
def _allowed(t_up, z_up, t_down, z_down, drift, slack_ns, i):
    """The offsets theta(0) exchange i allows, [-(x_down + d t4), x_up - d t1] widened by slack (ns)."""
    return -(z_down[i] + drift * t_down[i]) - slack_ns[i], (z_up[i] - drift * t_up[i]) + slack_ns[i]


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
    n = len(t_up)
    voters = 0
    for i in range(n):
        voters += among[i]
    points, v = np.empty(2 * voters), 0  # the voters' openings, then their closings
    for i in range(n):
        if among[i]:
            points[v], points[voters + v] = _allowed(t_up, z_up, t_down, z_down, drift, slack_ns, i)
            v += 1
    covered, most, theta = 0, -1, 0.0
    for j in _order(points):  # stable: at equal values openings come first
        covered += 1 if j < voters else -1
        if covered > most:
            most, theta = covered, points[j]
    agree = np.empty(n, np.bool_)
    for i in range(n):
        lo, hi = _allowed(t_up, z_up, t_down, z_down, drift, slack_ns, i)
        agree[i] = lo <= theta and theta <= hi
    return agree


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
    n, newest = len(segment), segment.max()
    last = n - 1
    while segment[last] != newest:
        last -= 1
    t_ref = times[n - 1, 3]
    theta_ref = ((times[last, 1] - times[last, 0]) + (times[last, 2] - times[last, 3])) // 2
    t_up, z_up, t_down, z_down, slack = np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    current = np.empty(n, np.bool_)
    for i in range(n):
        t1, t2, t3, t4 = times[i, 0], times[i, 1], times[i, 2], times[i, 3]
        t_up[i], z_up[i] = (t1 - t_ref) / NS_PER_S, float(t2 - t1 - theta_ref)  # up + theta - theta_ref
        t_down[i], z_down[i] = (t4 - t_ref) / NS_PER_S, float(t4 - t3 + theta_ref)  # down - (theta - theta_ref)
        # what a drift error of sigmas sd (of the last fit) does over the exchange's age
        slack[i] = sigmas * prev_sd * max(-t_up[i], -t_down[i]) + 1_000.0
        current[i] = segment[i] == newest
    agree = consensus(t_up, z_up, t_down, z_down, prev_drift, slack, current)
    rank = np.zeros(newest + 1, np.int64)  # each segment's rank among those present
    for g in segment:
        rank[g] = 1
    for g in range(1, newest + 1):
        rank[g] += rank[g - 1]
    outside, group, keep = np.empty(n, np.bool_), np.empty(n, np.int64), np.empty(n, np.int64)
    n_keep, n_outside = 0, 0
    for i in range(n):
        agree[i] = agree[i] and current[i]
        outside[i] = current[i] and not agree[i]
        group[i] = -1 if outside[i] else rank[segment[i]] - 1
        if agree[i]:
            keep[n_keep], n_keep = i, n_keep + 1
        n_outside += outside[i]
    keep = keep[:n_keep]
    contested = 2 * n_outside >= n_keep  # no clear majority: the others may be right
    drift, sd = fit_drift(t_up, z_up, t_down, z_down, group, bin_ns / NS_PER_S, (t_ref % bin_ns) / NS_PER_S, q,
                          prior_drift, prior_sd, min_resid)
    if not np.isnan(drift):
        drift = min(max(drift, -max_drift), max_drift)
    # the offset at t_ref from the lower envelopes of the current segment's agreeing exchanges
    cu_t, cu_z, cd_t, cd_z = t_up[keep], z_up[keep], t_down[keep], z_down[keep]
    drift_bound = sigmas * sd
    # the signs as floats: an int constant is a literal type to numba, which would compile leg_envelope (and
    # its helpers) once for +1 and once for -1 (a third of the kernel's compile)
    e_up, a_up = leg_envelope(cu_t, cu_z, 1.0, drift, drift_bound, q, horizon_s, threshold_ns, 3)
    e_down, a_down = leg_envelope(cd_t, cd_z, -1.0, drift, drift_bound, q, horizon_s, threshold_ns, 3)
    theta_rel = 0.5 * (e_up - e_down)
    bound = 0.5 * (e_up + e_down) + drift_bound * 0.5 * (a_up + a_down)
    if contested:  # the bound reaches as far as the offsets the others allow (the far edge of the farthest)
        for i in range(n):
            if outside[i]:
                lo, hi = _allowed(t_up, z_up, t_down, z_down, drift, slack, i)
                bound = max(bound, abs(lo - theta_rel), abs(hi - theta_rel))
    settled = n_keep - step_span  # the newest step_span are on probation
    i_up, i_down = 0, 0  # the least settled detrended reading of each leg
    for j in range(1, max(1, settled)):
        i_up = j if cu_z[j] - drift * cu_t[j] < cu_z[i_up] - drift * cu_t[i_up] else i_up
        i_down = j if cd_z[j] + drift * cd_t[j] < cd_z[i_down] + drift * cd_t[i_down] else i_down
    armed = not contested and settled >= armed_after
    return (outside, theta_ref, theta_rel, drift, sd, max(0.0, bound), cu_z[i_up] - drift * cu_t[i_up],
            times[keep[i_up], 0], cd_z[i_down] + drift * cd_t[i_down], times[keep[i_down], 3], armed)
