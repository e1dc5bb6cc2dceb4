"""RSU clock offset and drift from NTP-style four-timestamp exchanges (pure: times are arguments).

t1 OBU send, t2 RSU receive, t3 RSU send, t4 OBU receive (t1, t4 OBU clock; t2, t3 RSU clock).
  offset theta = rsu_clock - obu_clock = ((t2 - t1) + (t3 - t4)) / 2
  round trip   delta = (t4 - t1) - (t3 - t2)

Model. The offset is a line in OBU time t (drift in ns per ns, i.e. ppm * 1e-6):
  theta(t) = theta0 + drift * (t - t0)
Each exchange gives two one-way readings, each a true delay (>= 0) plus or minus theta:
  x_up   = t2 - t1 = up   + theta(t1)        (OBU -> RSU)
  x_down = t4 - t3 = down - theta(t4)        (RSU -> OBU)
so theta(t) lies in [t3 - t4, t2 - t1]: a sample can never be further from the truth than
that interval, whose width is its round trip. Queueing only ever adds delay, so the *lower
envelope* of each reading is where the information is (Paxson 1998; Moon et al. 1999):

- drift: lower-tail least squares (see fit_drift): keep the lowest fraction q of each leg's
  detrended readings (the least-queued samples), fit x_up ~ a_up + d t and -x_down ~ -a_down + d t
  with one shared slope d, re-select with the new d, repeat; the fit is shrunk towards a prior
  (0 +- 100 ppm at start, the pre-step drift after a step) by its standard error, so a short
  window cannot produce a wild drift;
- offset at t_ref: the readings of the last offset_horizon are detrended with d and the mean of
  the lowest fraction q taken per leg:
    E_up   = lowmean_q(x_up - d (t1 - t_ref))   = theta(t_ref) + lowmean_q(up)
    E_down = lowmean_q(x_down + d (t4 - t_ref)) = lowmean_q(down) - theta(t_ref)
    theta(t_ref) = (E_up - E_down) / 2,  error = (lowmean_q(up) - lowmean_q(down)) / 2,
  i.e. half the asymmetry of the *least* delays of the two legs, not of the average ones
  (a lower-tail mean varies less than a single order statistic such as the minimum);
- uncertainty: (E_up + E_down) / 2, half the round trip of that lower envelope, which bounds the
  unknowable asymmetry since both legs are >= 0 (reported with every estimate);
- spikes: a delayed sample sits above the lower tail and moves neither drift nor offset;
- clock steps: queueing only ever adds delay, so a reading below the least (detrended) reading
  of its leg in the window by more than ``step_threshold_ns`` cannot be explained by its round
  trip (the newest ``step_span`` samples do not count towards that least reading: a post-step
  sample that escaped detection must not lower the bar for the next ones). ``step_confirm``
  such readings within ``step_span`` exchanges (held aside meanwhile, so they do not move the
  estimate; dropped as outliers if unconfirmed) mean the RSU clock stepped (or the route got
  shorter): the window restarts at the first of them, keeping the drift as prior (a step
  changes the phase, not the rate). A step of +s lowers x_down by s, one of -s lowers x_up.
  Steps below the threshold are absorbed as the offset window slides.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

NS_PER_S = 1_000_000_000
PPM_NS_PER_S = 1_000.0  # 1 ppm = 1 us per s = 1000 ns per s
MIN_RESID_NS = 50_000.0  # floor on the per-sample noise of a drift fit (no false certainty)
MIN_DRIFT_SD_PPM = 2.0  # floor on the sd of the drift carried over a clock step


@dataclass(frozen=True)
class SyncSample:
    t1_ns: int
    t2_ns: int
    t3_ns: int
    t4_ns: int

    @property
    def offset_ns(self) -> int:
        return ((self.t2_ns - self.t1_ns) + (self.t3_ns - self.t4_ns)) // 2

    @property
    def round_trip_ns(self) -> int:
        return (self.t4_ns - self.t1_ns) - (self.t3_ns - self.t2_ns)

    def brackets(self, theta_ns: float, slack_ns: float = 0.0) -> bool:
        """True when t3 - t4 - slack <= theta <= t2 - t1 + slack (theta is physically possible)."""
        return self.t3_ns - self.t4_ns - slack_ns <= theta_ns <= self.t2_ns - self.t1_ns + slack_ns


@dataclass(frozen=True)
class OffsetEstimate:
    """theta(t) = offset_ns + drift_ppm * 1e-6 * (t - at_ns), t in OBU ns."""

    offset_ns: int  # theta = rsu_clock - obu_clock at OBU time at_ns
    uncertainty_ns: int  # half the round trip of the lower envelope (bound on the asymmetry error)
    samples: int  # exchanges accepted so far
    drift_ppm: float = 0.0  # d theta / dt in parts per million (1 ppm = 1 us per s)
    at_ns: int = 0  # OBU time the offset refers to
    steps: int = 0  # RSU clock steps detected so far

    def offset_at_ns(self, t_obu_ns: int) -> int:
        """theta(t) = theta0 + drift * (t - t0)."""
        return self.offset_ns + round(self.drift_ppm * 1e-6 * (t_obu_ns - self.at_ns))

    def to_obu_ns(self, rsu_time_ns: int) -> int:
        """RSU reading -> OBU time: solve r = t + theta0 + d (t - t0) for t:
        t = t0 + (r - t0 - theta0) / (1 + d)."""
        return self.at_ns + round((rsu_time_ns - self.at_ns - self.offset_ns) / (1.0 + self.drift_ppm * 1e-6))

    def to_rsu_ns(self, obu_time_ns: int) -> int:
        """OBU time -> RSU reading: r = t + theta(t)."""
        return obu_time_ns + self.offset_at_ns(obu_time_ns)


@dataclass(frozen=True)
class _Envelope:
    """The least detrended one-way readings of a window: x_up - theta_ref - drift (t1 - t_ref) and
    x_down + theta_ref + drift (t4 - t_ref) (ns; drift in ns per s)."""

    t_ref_ns: int
    theta_ref_ns: int
    drift: float
    min_up: float
    min_down: float


def lowest(values: np.ndarray, q: float) -> np.ndarray:
    """Indices of the lowest max(1, ceil(q n)) entries of a (n,) array (the lower tail)."""
    k = min(len(values), max(1, int(np.ceil(q * len(values)))))
    return np.argpartition(values, k - 1)[:k]


def bin_tail_means(bins: np.ndarray, t: np.ndarray, r: np.ndarray, q: float) -> tuple[np.ndarray, np.ndarray]:
    """(mean t, mean of the lowest fraction q of r) per bin, shapes (m,), bins ascending.

    Bins holding fewer than half the median count (half-filled bins at the window edges) are
    left out: their lower tail is a weaker lower bound.
    """
    order = np.lexsort((r, bins))  # by bin, then by r: each bin's lower tail comes first
    b, t_s, r_s = bins[order], t[order], r[order]
    starts = np.flatnonzero(np.r_[True, b[1:] != b[:-1]])
    ends = np.r_[starts[1:], len(b)]
    counts = ends - starts
    k = np.maximum(1, np.ceil(q * counts).astype(int))  # lower-tail size per bin
    t_cum, r_cum = np.r_[0.0, np.cumsum(t_s)], np.r_[0.0, np.cumsum(r_s)]
    keep = counts >= 0.5 * np.median(counts)
    t_bin = (t_cum[ends] - t_cum[starts]) / counts
    r_bin = (r_cum[starts + k] - r_cum[starts]) / k
    return t_bin[keep], r_bin[keep]


def shared_slope(t_a: np.ndarray, y_a: np.ndarray, t_b: np.ndarray, y_b: np.ndarray,
                 min_resid: float) -> tuple[float, float] | None:
    """Least-squares slope shared by two point groups with their own intercepts, and its std error.

    d = sum_g sum_i (t_i - tbar_g)(y_i - ybar_g) / Sxx,  Sxx = sum_g sum_i (t_i - tbar_g)^2,
    se = sqrt(s^2 / Sxx),  s^2 = RSS / (m - 3) floored at min_resid^2;
    None unless each group has >= 3 points spread in t.
    """
    if min(len(t_a), len(t_b)) < 3:
        return None
    ta, tb = t_a - t_a.mean(), t_b - t_b.mean()
    ya, yb = y_a - y_a.mean(), y_b - y_b.mean()
    sxx = float(ta @ ta + tb @ tb)
    if sxx <= 0.0:
        return None
    d = float(ta @ ya + tb @ yb) / sxx
    rss = float(np.sum((ya - d * ta) ** 2) + np.sum((yb - d * tb) ** 2))
    return d, float(np.sqrt(max(rss / (len(t_a) + len(t_b) - 3), min_resid**2) / sxx))


def fit_drift(bins_up: np.ndarray, dt_up: np.ndarray, x_up: np.ndarray, bins_down: np.ndarray,
              dt_down: np.ndarray, x_down: np.ndarray, q: float, prior: tuple[float, float],
              min_resid: float, iters: int = 2) -> tuple[float, float]:
    """(drift, sd) in ns per s of the lower envelopes of both legs, shrunk to a prior.

    Per sub-window (bin) and leg, the lower-tail mean of the readings detrended with the current
    drift d is the envelope at the bin's mean time; the envelopes of x_up (slope +d) and of
    -x_down (slope +d) get one shared least-squares slope s (shared_slope, std error se from the
    scatter of the bins, but never below the expected scatter tail_mean_sd / sqrt(samples per
    bin), so that a few bins lying on a line by chance do not fake certainty). With the prior
    N(d0, sd0^2), the Gaussian posterior is
      d = d0 + w (s - d0),  w = sd0^2 / (sd0^2 + se^2),  sd = (1 / sd0^2 + 1 / se^2)^(-1/2)
    so a short window leans on the prior (0 +- 100 ppm at start, the pre-step drift after a
    step); the fit is repeated with the new d (detrending inside a bin hardly matters).
    """
    d0, sd0 = prior
    d, sd = d0, sd0
    for _ in range(iters):
        tu, eu = bin_tail_means(bins_up, dt_up, x_up - d * dt_up, q)
        td, ed = bin_tail_means(bins_down, dt_down, x_down + d * dt_down, q)
        # a bin envelope scatters at least by the lower-tail-mean noise of its samples
        per_bin = max(tail_mean_sd(x_up - d * dt_up, q), tail_mean_sd(x_down + d * dt_down, q)) / np.sqrt(
            max(1.0, len(dt_up) / max(len(tu), 1)))
        fit = shared_slope(tu, eu + d * tu, td, -(ed - d * td), max(min_resid, per_bin))
        if fit is None:
            return d0, sd0
        s, se = fit
        d, sd = d0 + sd0**2 / (sd0**2 + se**2) * (s - d0), float((1.0 / sd0**2 + 1.0 / se**2) ** -0.5)
    return d, sd


def tail_mean_sd(r: np.ndarray, q: float) -> float:
    """Per-observation sd of the mean of the lowest fraction q of r (from its influence function):

    L = (1/q) int_0^q Q(p) dp,  IF(x) = min(x - Q_q, 0) / q + const, so
    var = E[(x - Q_q)^2 | tail] / q - (mean_tail - Q_q)^2.
    """
    tail = np.sort(r[lowest(r, q)])
    dev = tail - tail[-1]  # tail[-1] ~ Q_q
    return float(np.sqrt(max(np.mean(dev**2) / q - np.mean(dev) ** 2, 0.0)))


def offset_horizon_s(sd_up: float, sd_down: float, rate_hz: float, drift_sd: float) -> float:
    """Offset window length h (s) balancing noise against the lag error of an uncertain drift.

    The offset of the last h seconds has variance (sd_up^2 + sd_down^2) / (4 rate h) (two lower-
    tail means, halved) and, with drift error sd, a lag error sd h / 2 (its samples are h / 2 old
    on average). d/dh [A / h + B h^2] = 0  =>  h = (A / 2B)^(1/3) = ((sd_up^2 + sd_down^2) / (2 rate sd^2))^(1/3).
    """
    if drift_sd <= 0.0 or rate_hz <= 0.0:
        return float("inf")
    return float(((sd_up**2 + sd_down**2) / (2.0 * rate_hz * drift_sd**2)) ** (1.0 / 3.0))


def envelope_offset(dt_up: np.ndarray, x_up: np.ndarray, dt_down: np.ndarray, x_down: np.ndarray,
                    drift: float, q: float) -> tuple[float, float]:
    """(theta, envelope round trip) at dt = 0 from the detrended lower tails (see module doc).

    dt_* are OBU times (s) relative to the reference time, x_* the one-way readings (ns), drift ns/s.
    E = mean of the lowest fraction q (a lower-tail mean has less variance than one order statistic).
    """
    u, w = x_up - drift * dt_up, x_down + drift * dt_down
    e_up = float(u[lowest(u, q)].mean())  # theta(t_ref) + lower-tail mean of up
    e_down = float(w[lowest(w, q)].mean())  # lower-tail mean of down - theta(t_ref)
    return 0.5 * (e_up - e_down), e_up + e_down


class ClockSync:
    """Offset and drift of one RSU clock from a bounded, time-limited window of exchanges.

    window: at most this many samples are kept (memory bound; 10 Hz x 60 s = 600);
    horizon_ns: samples older than this (by t4, relative to the newest) are dropped; the drift
    is fitted over the whole window, the offset from the samples of the last offset_horizon_ns;
    quantile: the lower-tail fraction taken as the envelope of each leg.
    """

    def __init__(self, window: int = 600, *, horizon_ns: int = 60 * NS_PER_S,
                 offset_horizon_ns: int = 30 * NS_PER_S, min_offset_horizon_ns: int = 2 * NS_PER_S,
                 bin_ns: int = 2 * NS_PER_S, quantile: float = 0.1, drift_prior_ppm: float = 100.0,
                 max_drift_ppm: float = 500.0, step_threshold_ns: int = 2_000_000, step_confirm: int = 3,
                 step_span: int = 10, step_armed_after: int = 10):
        self.horizon_ns, self.offset_horizon_ns, self.quantile = horizon_ns, offset_horizon_ns, quantile
        self.min_offset_horizon_ns, self.bin_ns = min_offset_horizon_ns, bin_ns
        self.max_drift = max_drift_ppm * PPM_NS_PER_S
        self.step_threshold_ns, self.step_confirm, self.step_armed_after = step_threshold_ns, step_confirm, step_armed_after
        self.step_span = step_span
        self._samples: deque[SyncSample] = deque(maxlen=window)
        self._suspects: list[tuple[int, SyncSample]] = []  # (arrival number, sample) held aside
        self._last: SyncSample | None = None
        self._total = 0
        self._steps = 0
        self.outliers_dropped = 0
        self._prior = (0.0, drift_prior_ppm * PPM_NS_PER_S)  # drift prior (mean, sd) in ns/s
        self._drift = (0.0, drift_prior_ppm * PPM_NS_PER_S)  # latest drift fit (mean, sd) in ns/s
        self._fit: OffsetEstimate | None = None  # cache, None when stale
        self._envelope: _Envelope | None = None  # least readings of the window, with the cached fit

    @property
    def steps_detected(self) -> int:
        return self._steps

    def add(self, sample: SyncSample) -> bool:
        """Add an exchange; False (and ignored) when its timestamps are inconsistent."""
        if sample.round_trip_ns < 0 or sample.t4_ns < sample.t1_ns:
            return False
        self._total += 1
        self._last = sample
        self._drop_old_suspects()
        if self._contradicts(sample):
            self._suspects.append((self._total, sample))
            if len(self._suspects) >= self.step_confirm:
                self._restart_after_step()
            return True
        self._samples.append(sample)
        while sample.t4_ns - self._samples[0].t4_ns > self.horizon_ns:
            self._samples.popleft()
        self._fit = None
        return True

    def estimate(self) -> OffsetEstimate | None:
        """The estimate at the OBU receive time (t4) of the latest accepted exchange."""
        return None if self._last is None else self.estimate_at(self._last.t4_ns)

    def estimate_at(self, t_obu_ns: int) -> OffsetEstimate | None:
        """The estimate extrapolated to OBU time t: theta(t) = theta0 + drift (t - t0)."""
        fit = self._current_fit()
        if fit is None:
            return None
        return OffsetEstimate(fit.offset_at_ns(t_obu_ns), fit.uncertainty_ns, self._total, fit.drift_ppm,
                              t_obu_ns, self._steps)

    def naive(self) -> OffsetEstimate | None:
        """The latest single exchange, as a plain NTP client without filtering would use."""
        last = self._last
        if last is None:
            return None
        return OffsetEstimate(last.offset_ns, last.round_trip_ns // 2, self._total, 0.0, last.t4_ns, self._steps)

    def to_obu_ns(self, rsu_time_ns: int) -> int | None:
        """RSU clock reading -> OBU clock using offset and drift; None before the first exchange."""
        est = self.estimate()
        return None if est is None else est.to_obu_ns(rsu_time_ns)

    def to_rsu_ns(self, obu_time_ns: int) -> int | None:
        """OBU clock reading -> RSU clock; None before the first exchange."""
        est = self.estimate()
        return None if est is None else est.to_rsu_ns(obu_time_ns)

    # --- internals -------------------------------------------------------------------------
    def _contradicts(self, sample: SyncSample) -> bool:
        """A reading below the window's least (detrended) reading of its leg by more than the
        threshold: queueing only adds delay, so only a clock step (or a shorter route) explains it."""
        if len(self._samples) - self.step_span < self.step_armed_after:
            return False
        self._current_fit()
        env = self._envelope
        r_up = (sample.t2_ns - sample.t1_ns - env.theta_ref_ns) - env.drift * (sample.t1_ns - env.t_ref_ns) / NS_PER_S
        r_down = (sample.t4_ns - sample.t3_ns + env.theta_ref_ns) + env.drift * (sample.t4_ns - env.t_ref_ns) / NS_PER_S
        return min(r_up - env.min_up, r_down - env.min_down) < -self.step_threshold_ns

    def _drop_old_suspects(self) -> None:
        """Suspects not confirmed within step_span exchanges are dropped as outliers (a reading
        below the envelope is never ordinary queueing: a glitch, not data to keep)."""
        if self._suspects and self._suspects[0][0] <= self._total - self.step_span:
            self.outliers_dropped += len(self._suspects)
            self._suspects.clear()

    def _restart_after_step(self) -> None:
        """The RSU clock stepped: restart the window from the first suspect on, keep the rate as prior."""
        self._current_fit()  # the pre-step drift becomes the prior of the new window
        self._prior = (self._drift[0], max(self._drift[1], MIN_DRIFT_SD_PPM * PPM_NS_PER_S))
        first_ns = self._suspects[0][1].t4_ns
        after = [s for s in self._samples if s.t4_ns >= first_ns] + [s for _, s in self._suspects]
        self._samples = deque(sorted(after, key=lambda s: s.t4_ns), maxlen=self._samples.maxlen)
        self._suspects.clear()
        self._steps += 1
        self._fit = None

    def _current_fit(self) -> OffsetEstimate | None:
        if self._fit is None and self._samples:
            self._fit = self._compute_fit()
        return self._fit

    def _compute_fit(self) -> OffsetEstimate:
        s = self._samples
        t1, t2, t3, t4 = np.array([(x.t1_ns, x.t2_ns, x.t3_ns, x.t4_ns) for x in s], dtype=np.int64).T
        newest = int(np.argmax(t4))
        t_ref, theta_ref = int(t4[newest]), s[newest].offset_ns  # subtracted first: floats stay small, exact
        x_up = (t2 - t1 - theta_ref).astype(float)  # up + (theta - theta_ref), ns
        x_down = (t4 - t3 + theta_ref).astype(float)  # down - (theta - theta_ref), ns
        dt_up, dt_down = (t1 - t_ref) / NS_PER_S, (t4 - t_ref) / NS_PER_S  # s
        drift, sd = fit_drift(t1 // self.bin_ns, dt_up, x_up, t4 // self.bin_ns, dt_down, x_down, self.quantile,
                              self._prior, MIN_RESID_NS)
        drift = float(np.clip(drift, -self.max_drift, self.max_drift))
        self._drift = (drift, sd)
        settled = slice(0, max(1, len(s) - self.step_span))  # the newest step_span are still on probation
        self._envelope = _Envelope(t_ref, theta_ref, drift, float(np.min((x_up - drift * dt_up)[settled])),
                                   float(np.min((x_down + drift * dt_down)[settled])))
        recent = dt_down >= -self._offset_horizon_s(dt_up, x_up, dt_down, x_down, drift, sd)
        theta_rel, env_rtt = envelope_offset(dt_up[recent], x_up[recent], dt_down[recent], x_down[recent],
                                             drift, self.quantile)
        return OffsetEstimate(theta_ref + round(theta_rel), max(0, int(np.ceil(0.5 * env_rtt))), self._total,
                              drift / PPM_NS_PER_S, t_ref, self._steps)

    def _offset_horizon_s(self, dt_up, x_up, dt_down, x_down, drift: float, drift_sd: float) -> float:
        """offset_horizon_s() for this window, within [min_offset_horizon, offset_horizon]."""
        span_s = float(dt_down[-1] - dt_down[0])
        rate_hz = (len(dt_down) - 1) / span_s if span_s > 0.0 else 0.0
        h = offset_horizon_s(tail_mean_sd(x_up - drift * dt_up, self.quantile),
                             tail_mean_sd(x_down + drift * dt_down, self.quantile), rate_hz, drift_sd)
        return float(np.clip(h, self.min_offset_horizon_ns / NS_PER_S, self.offset_horizon_ns / NS_PER_S))
