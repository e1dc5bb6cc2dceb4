"""Lower-envelope statistics of one-way clock readings (pure numpy; see clock_sync for the model).

A one-way reading is a true delay (>= 0) plus or minus the clock offset; queueing only ever adds
delay, so the information is in the lower tail of each leg's readings (Paxson 1998; Moon et al.
1999). Readings are detrended with a drift d (ns per s): an up reading z_up = up + theta(t) has
z_up - d t = up + theta(0), a down reading z_down = down - theta(t) has z_down + d t = down -
theta(0). With sign s = +1 (up) or -1 (down): z - s d t is the detrended reading of either leg.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

# Readings more than this above their leg's least (detrended) reading are buffered or queued
# far beyond any drift trend (500 ppm x 60 s = 30 ms): never part of a lower envelope.
QUEUED_NS = 200_000_000.0


@dataclass(frozen=True)
class Leg:
    """The readings of one leg (in one clock segment where that matters), arrays of shape (n,).

    t_s: OBU time of the reading relative to the reference time (s; t1 for up, t4 for down);
    z_ns: the reading (x_up or x_down, ns, relative to a reference offset); sign: +1 up, -1 down.
    """

    t_s: np.ndarray
    z_ns: np.ndarray
    sign: int

    def detrended(self, drift: float) -> np.ndarray:
        """z - sign d t (ns): delay + const; shape (n,)."""
        return self.z_ns - self.sign * drift * self.t_s

    def take(self, keep: np.ndarray) -> Leg:
        return Leg(self.t_s[keep], self.z_ns[keep], self.sign)


def lowest(values: np.ndarray, q: float) -> np.ndarray:
    """Indices of the lowest max(1, ceil(q n)) entries of a (n,) array (the lower tail)."""
    k = _tail_size(len(values), q)
    return np.argpartition(values, k - 1)[:k]


def _tail_size(n: int, q: float) -> int:
    """max(1, ceil(q n)), at most n: how many readings make the lower tail of n."""
    return min(n, max(1, math.ceil(q * n)))


def bin_tail_means(bins: np.ndarray, t: np.ndarray, r: np.ndarray, q: float) -> tuple[np.ndarray, np.ndarray]:
    """(mean t, mean of the lowest fraction q of r) per bin, shapes (m,), bins ascending.

    Bins holding fewer than half the median count (half-filled bins at the window edges) are
    left out: their lower tail is a weaker lower bound.
    """
    return _Bins.of(bins, q).tail_means(bins, t, r)


@dataclass(frozen=True)
class _Bins:
    """Where each bin starts and ends in readings sorted by bin, its count, the size of its lower
    tail and whether it is kept, shapes (m,): they depend on the bins only, not on the readings'
    order within a bin, so a fit finds them once per leg for both drift iterations."""

    starts: np.ndarray
    ends: np.ndarray
    counts: np.ndarray
    tails: np.ndarray  # lower-tail size per bin, max(1, ceil(q counts))
    keep: np.ndarray | None  # None: every bin is kept

    @staticmethod
    def of(bins: np.ndarray, q: float) -> _Bins:
        b = np.sort(bins)  # = bins[np.lexsort((r, bins))] for any r
        # (np.concatenate, not np.r_: the same arrays without np.r_'s parsing, this runs per clock fit)
        starts = np.flatnonzero(np.concatenate(([True], b[1:] != b[:-1])))
        ends = np.concatenate((starts[1:], [len(b)]))
        counts = ends - starts
        k = np.maximum(1, np.ceil(q * counts).astype(int))  # lower-tail size per bin
        keep = counts >= 0.5 * median_of_ints(counts.tolist())
        return _Bins(starts, ends, counts, k, None if keep.all() else keep)

    def tail_means(self, bins: np.ndarray, t: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """bin_tail_means of readings (t, r) in these bins, shapes (n,) -> (m,)."""
        order = np.lexsort((r, bins))  # by bin, then by r: each bin's lower tail comes first
        t_cum, r_cum = _prefix_sums(t[order]), _prefix_sums(r[order])
        t_bin = (t_cum[self.ends] - t_cum[self.starts]) / self.counts
        r_bin = (r_cum[self.starts + self.tails] - r_cum[self.starts]) / self.tails
        if self.keep is None:
            return t_bin, r_bin
        return t_bin[self.keep], r_bin[self.keep]


def _prefix_sums(x: np.ndarray) -> np.ndarray:
    """[0, x0, x0 + x1, ...], shape (n + 1,): np.concatenate(([0.0], np.cumsum(x))) without the copy."""
    out = np.empty(len(x) + 1)
    out[0] = 0.0
    np.cumsum(x, out=out[1:])
    return out


def median_of_ints(values: list[int]) -> float:
    """np.median of a few integers (exact: the middle one, or the mean of the middle two, as a float)."""
    s = sorted(values)
    h = len(s) // 2
    return float(s[h]) if len(s) % 2 else (s[h - 1] + s[h]) / 2


def lower_quartile(values: list[float]) -> float:
    """np.percentile(values, 25) of a few finite floats, bit for bit: the linear method's virtual
    index v = 0.25 (n - 1), a = s[floor v], b = s[floor v + 1], g = v - floor v, and numpy's lerp
    a + (b - a) g (b - (b - a)(1 - g) when g >= 0.5)."""
    s = sorted(values)
    v = 0.25 * (len(s) - 1)
    i = int(v)
    g = v - i
    a, b = s[i], s[min(i + 1, len(s) - 1)]
    diff = b - a
    return b - diff * (1 - g) if g >= 0.5 else a + diff * g


def shared_slope(groups: list[tuple[np.ndarray, np.ndarray]], min_resid: float) -> tuple[float, float] | None:
    """Least-squares slope shared by point groups (t, y), each with its own intercept, and its std error.

    d = sum_g sum_i (t_i - tbar_g)(y_i - ybar_g) / Sxx,  Sxx = sum_g sum_i (t_i - tbar_g)^2,
    se = sqrt(s^2 / Sxx),  s^2 = RSS / (m - G - 1) floored at min_resid^2 (m points, G groups);
    None unless two groups have >= 3 points spread in t.
    """
    groups = [(t, y) for t, y in groups if len(t) >= 2]
    if sum(len(t) >= 3 for t, _ in groups) < 2:
        return None
    tc = [t - t.sum() / len(t) for t, _ in groups]  # (x.sum() / n: the very division np.mean makes)
    yc = [y - y.sum() / len(y) for _, y in groups]
    sxx = float(sum(a @ a for a in tc))
    if sxx <= 0.0:
        return None
    d = float(sum(a @ b for a, b in zip(tc, yc))) / sxx
    rss = float(sum(((b - d * a) ** 2).sum() for a, b in zip(tc, yc)))
    dof = max(1, sum(len(a) for a in tc) - len(tc) - 1)
    return d, float(np.sqrt(max(rss / dof, min_resid**2) / sxx))


def tail_mean_sd(r: np.ndarray, q: float) -> float:
    """Per-observation sd of the mean of the lowest fraction q of r (from its influence function):

    L = (1/q) int_0^q Q(p) dp,  IF(x) = min(x - Q_q, 0) / q + const, so
    var = E[(x - Q_q)^2 | tail] / q - (mean_tail - Q_q)^2.
    """
    k = _tail_size(len(r), q)
    tail = np.sort(np.partition(r, k - 1)[:k])  # the k lowest values, ascending
    dev = tail - tail[-1]  # tail[-1] ~ Q_q
    # (sum / k: the very division np.mean makes)
    return float(np.sqrt(max((dev**2).sum() / k / q - (dev.sum() / k) ** 2, 0.0)))


def _bin_envelopes(leg: Leg, bins: np.ndarray, layout: _Bins, r: np.ndarray, drift: float,
                   q: float) -> tuple[np.ndarray, np.ndarray]:
    """(t, sign * (envelope + sign d t)) per bin of a leg: points on a line of slope d, shapes (m,).

    ``bins``: each reading's bin floor((t + phase_s) / bin_s) (edges at t = k bin_s - phase_s, fixed
    in absolute time as the reference time moves), ``layout`` their _Bins; ``r``: the readings
    detrended with ``drift``."""
    t = leg.t_s
    unqueued = r <= r.min() + QUEUED_NS  # buffered readings say nothing about the envelope's slope
    if not unqueued.all():
        bins, t, r = bins[unqueued], t[unqueued], r[unqueued]
        layout = _Bins.of(bins, q)
    t_bin, e_bin = layout.tail_means(bins, t, r)
    return t_bin, leg.sign * e_bin + drift * t_bin


def fit_drift(legs: list[Leg], bin_s: float, phase_s: float, q: float, prior: tuple[float, float],
              min_resid: float, iters: int = 2) -> tuple[float, float]:
    """(drift, sd) in ns per s of the lower envelopes of all legs and segments, shrunk to a prior.

    Per sub-window (bin of bin_s seconds, edges at k bin_s - phase_s) and leg, the lower-tail
    mean of the readings detrended with the current drift d is the envelope at the bin's mean
    time; the envelopes (signed so that every leg rises with slope d) get one shared least-squares
    slope s with an intercept per leg and clock segment (a step moves the intercepts, not the
    rate: shared_slope, std error se from the scatter of the bins, but never below the expected
    scatter tail_mean_sd / sqrt(samples per bin), so that a few bins lying on a line by chance do
    not fake certainty). Bins whose envelope lies above the grouped Theil-Sen line by more than
    3 such sd (a leg congested or buffered for a whole bin) are left out. With the prior
    N(d0, sd0^2), the Gaussian posterior is
      d = d0 + w (s - d0),  w = sd0^2 / (sd0^2 + se^2),  sd = (1 / sd0^2 + 1 / se^2)^(-1/2).
    """
    d0, sd0 = prior
    d, sd = d0, sd0
    legs = [leg for leg in legs if len(leg.t_s) >= 3]
    if not legs:
        return d0, sd0
    n = sum(len(leg.t_s) for leg in legs)
    bins = [np.floor((leg.t_s + phase_s) / bin_s) for leg in legs]  # the drift moves no reading across bins
    layouts = [_Bins.of(b, q) for b in bins]
    # shared_slope needs two groups of >= 3 bins, and leaving out queued readings or congested
    # bins never adds a bin: without two legs of >= 3 bins (a young window) the fit is the prior
    if sum(len(layout.starts) >= 3 for layout in layouts) < 2:
        return d0, sd0
    for _ in range(iters):
        detrended = [leg.detrended(d) for leg in legs]  # once per leg and drift: envelopes and their noise
        points = [_bin_envelopes(leg, b, layout, r, d, q) for leg, b, layout, r in zip(legs, bins, layouts, detrended)]
        # a bin envelope scatters at least by the lower-tail-mean noise of its samples
        n_bins = sum(len(t) for t, _ in points)
        per_bin = max(tail_mean_sd(r, q) for r in detrended) / np.sqrt(max(1.0, n / max(n_bins, 1)))
        floor = max(min_resid, per_bin)
        robust = theil_sen_slope(points)
        if robust is not None:
            points = [_below_line(t, y, leg.sign, robust, 3.0 * floor) for (t, y), leg in zip(points, legs)]
        fit = shared_slope(points, floor)
        if fit is None:
            return d0, sd0
        s, se = fit
        d, sd = d0 + sd0**2 / (sd0**2 + se**2) * (s - d0), float((1.0 / sd0**2 + 1.0 / se**2) ** -0.5)
    return d, sd


def theil_sen_slope(groups: list[tuple[np.ndarray, np.ndarray]]) -> float | None:
    """Median of the pairwise slopes (y_j - y_i) / (t_j - t_i) within each group (Theil 1950, Sen 1968,
    grouped so that each group keeps its own intercept); None without a pair."""
    slopes = []
    for t, y in groups:
        i, j = _pairs(len(t))
        dt = t[j] - t[i]
        ok = dt != 0.0
        slopes.append((y[j] - y[i]) / dt if ok.all() else (y[j] - y[i])[ok] / dt[ok])
    slopes = np.concatenate(slopes) if slopes else np.empty(0)
    return median_of_floats(slopes) if len(slopes) else None


def median_of_floats(x: np.ndarray) -> float:
    """np.median of a (n,) array of finite floats, bit for bit: the middle value, or (a + b) / 2 of
    the middle two (np.median's mean of two), from a partition instead of its generic reduction."""
    h = len(x) // 2
    if len(x) % 2:
        return float(np.partition(x, h)[h])
    part = np.partition(x, (h - 1, h))
    return (float(part[h - 1]) + float(part[h])) / 2


@lru_cache(maxsize=128)
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """np.triu_indices(n, 1), read-only: a pure function of n (a fit has a few dozen bins per group)."""
    i, j = np.triu_indices(n, 1)
    i.flags.writeable = j.flags.writeable = False
    return i, j


def _below_line(t: np.ndarray, y: np.ndarray, sign: int, d: float, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """The bins of one group whose envelope is not congested: sign (y - d t) <= c + limit, c the lower
    quartile of sign (y - d t) over the group (a congested bin lies above the envelope line)."""
    if len(t) < 4:
        return t, y
    excess = sign * (y - d * t)
    keep = excess <= lower_quartile(excess.tolist()) + limit
    return (t, y) if keep.all() else (t[keep], y[keep])


@dataclass(frozen=True)
class TailMean:
    """The lower-tail mean of one leg's detrended readings: value (ns) and mean age (s, >= 0)."""

    value_ns: float
    age_s: float


def tail_mean(leg: Leg, drift: float, q: float) -> TailMean:
    """E = mean of the lowest fraction q of the detrended readings, and their mean age -t."""
    return _tail_mean(leg.detrended(drift), leg.t_s, q)


def _tail_mean(r: np.ndarray, t_s: np.ndarray, q: float) -> TailMean:
    """tail_mean of readings already detrended (r) at times t_s, shapes (n,)."""
    low = lowest(r, q)
    k = len(low)  # (sum / k: the very division np.mean makes, without its generic reduction)
    return TailMean(float(r[low].sum() / k), float(max(0.0, -(t_s[low].sum() / k))))


def leg_envelope(leg: Leg, drift: float, drift_bound: float, q: float, horizon_s: float, margin_ns: float,
                 min_readings: int = 3) -> TailMean:
    """The lower-tail mean of a leg over the horizon that keeps its bound E + drift_bound * age low.

    Readings more than QUEUED_NS above the leg's least one (buffered) are never part of its lower
    tail. Starts from the readings of the last horizon_s (at least the newest min_readings) and
    doubles the horizon while that bounds the leg better by more than margin_ns: a drift error of
    at most drift_bound (ns/s) moves a reading of age a by drift_bound a, so an older, un-queued
    envelope is worth more than a recent one whose every reading was buffered.
    """
    r = leg.detrended(drift)
    usable = np.flatnonzero(r <= r.min() + QUEUED_NS)
    order = usable[np.argsort(-leg.t_s[usable])]  # un-queued readings, newest first
    ages = -leg.t_s[order]
    best, best_bound, h = None, np.inf, horizon_s
    while True:
        count = max(min(min_readings, len(order)), int(np.searchsorted(ages, h, side="right")))
        env = _tail_mean(r[order[:count]], leg.t_s[order[:count]], q)  # = tail_mean(leg.take(...), drift, q)
        bound = env.value_ns + drift_bound * env.age_s
        if best is None or bound < best_bound - margin_ns:
            best, best_bound = env, bound
        if h >= ages[-1]:
            return best
        h *= 2.0


def _allowed(up: Leg, down: Leg, drift: float, slack_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The offsets theta(0) each exchange allows, [-(x_down + d t4), x_up - d t1] widened by slack (ns)."""
    return -down.detrended(drift) - slack_ns, up.detrended(drift) + slack_ns


def consensus(up: Leg, down: Leg, drift: float, slack_ns: np.ndarray, among: np.ndarray) -> np.ndarray:
    """Which exchanges agree on the offset most of them allow (Marzullo 1984), bool shape (n,).

    up and down hold the two readings of the same n exchanges; only those in ``among`` (bool
    (n,)) vote. Exchange i allows theta(0) in [-(x_down + d t4), x_up - d t1] (both delays >= 0),
    widened by slack_ns[i] for the drift error; genuine exchanges all contain the true offset, so
    the point covered by the most intervals is kept and an exchange whose interval misses it (a
    forged or stepped reply among agreeing ones) is not.
    """
    lo, hi = _allowed(up, down, drift, slack_ns)
    points = np.concatenate((lo, hi) if among.all() else (lo[among], hi[among]))  # the voters' openings, closings
    voters = len(points) // 2
    # by value, an opening before a closing at the same value: a stable sort of points whose openings
    # come first (= np.lexsort((-kinds, points)), kinds +1 opening, -1 closing)
    order = np.argsort(points, kind="stable")
    kinds = np.where(order < voters, 1.0, -1.0)  # of the sorted points
    theta = points[order[int(np.argmax(np.cumsum(kinds)))]]  # start of a most-covered segment
    return (lo <= theta) & (theta <= hi)


def disputed_ns(up: Leg, down: Leg, drift: float, slack_ns: np.ndarray, outside: np.ndarray,
                theta_ns: float) -> float:
    """How far from theta_ns the offsets allowed by the exchanges in ``outside`` reach (ns, the far
    edge of the farthest): what the bound must cover when those may be the genuine ones."""
    lo, hi = _allowed(up.take(outside), down.take(outside), drift, slack_ns[outside])
    return float(np.max(np.maximum(np.abs(lo - theta_ns), np.abs(hi - theta_ns)), initial=0.0))
