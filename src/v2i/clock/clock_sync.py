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
envelope* of each reading is where the information is (clock_envelope):

- consensus: genuine exchanges all bracket the true offset, so in the current clock segment only
  the exchanges whose intervals contain the offset most of them allow are used (Marzullo's
  intersection, clock_envelope.consensus); the others are counted in ``outliers_rejected``.
  Without a clear majority (a third or more disagree) the bound also covers what the others
  allow, and the fit does not count as converged;
- drift: lower-tail least squares over the whole window (clock_envelope.fit_drift), one slope
  shared by both legs and by every clock segment (an RSU clock step moves the phase, not the
  rate, so the samples before a step keep informing the drift), shrunk towards 0 +- 100 ppm;
- offset at t_ref (the newest t4): the readings of the current segment are detrended with the
  drift and the mean of the lowest fraction q taken per leg:
    E_up   = lowmean_q(x_up - d (t1 - t_ref))   = theta(t_ref) + lowmean_q(up)
    E_down = lowmean_q(x_down + d (t4 - t_ref)) = lowmean_q(down) - theta(t_ref)
    theta(t_ref) = (E_up - E_down) / 2,  error = (lowmean_q(up) - lowmean_q(down)) / 2,
  over each leg's last offset_horizon by that leg's own time (t1 up, t4 down: an exchange that
  completes tens of seconds late counts where it was measured), further back when every recent
  reading of a leg was buffered (clock_envelope.leg_envelope). The whole segment is used, not a
  shorter horizon: the drift comes from the same readings, so their errors are correlated; for
  n readings over T seconds with a least-squares slope, the offset of the last h seconds has
  variance s^2 / n (T / h + 6 h / T - 3 h^2 / T^2), smallest at h = T. offset_horizon_ns only
  guards against a drift that is not constant over long windows;
- uncertainty, a bound on |estimate - truth| at OBU time t:
    U(t) = (E_up + E_down) / 2 + k sd (a_up + a_down) / 2 + k sd |t - t_ref|
  the first term is half the round trip of the lower envelope, which bounds the asymmetry since
  both legs are >= 0; the others bound the drift error (k = bound_sigmas standard deviations)
  acting on envelope readings of mean age a and on the extrapolation to t (U grows while no
  exchange arrives). While a step is suspected but not confirmed, U also covers the step;
- outliers and clock steps: queueing only ever adds delay, so against a converged fit (a clear
  majority and step_armed_after settled samples in the current segment) a reading below the
  least detrended reading of its leg by more than step_threshold_ns (plus k sd times the time
  between the two readings) cannot be explained by its round trip. Each sample bounds the step
  s the RSU clock would have made: after a step s, x_up rises and x_down falls by s, so with
  a, b its readings above the least ones, s lies in [-b - thr, a + thr]. A sample whose
  interval excludes 0 is a *suspect*: held aside (never averaged in) under the hypothesis S =
  the intersection of the suspects' intervals. A suspect disjoint from S, or an ordinary sample
  sent after the first suspect came back whose interval is disjoint from S (a genuine reply
  that still agrees with the old clock, e.g. between forged replies), refutes the hypothesis:
  its suspects are rejected and counted in ``outliers_rejected``, as are suspects left
  unconfirmed for step_span exchanges. step_confirm mutually consistent suspects confirm a
  step: a new clock segment starts with them (and with the samples since the first suspect
  that agree with S). A late reply stamped before the step (it agrees with the previous
  segment) joins the previous segment instead of suspecting a step back. Steps too small to
  stand out this way are absorbed as the offset window slides.
"""

from __future__ import annotations

import math
from array import array
from bisect import bisect_right
from collections import deque
from dataclasses import dataclass, field
from operator import itemgetter

import numpy as np

from v2i.clock.clock_envelope import fit_window

NS_PER_S = 1_000_000_000
PPM_NS_PER_S = 1_000.0  # 1 ppm = 1 us per s = 1000 ns per s
MIN_RESID_NS = 50_000.0  # floor on the per-sample noise of a drift fit (no false certainty)
# What the bound becomes while the RSU has not been heard promptly (ClockSync silence_ns): its clock
# may have stepped meanwhile by any amount, which nothing bounds; an hour stands for "unbounded" in an
# int64 ns field (no mode fuses through it, see obu_service.mode_inputs)
SILENT_BOUND_NS = 3_600 * NS_PER_S
_first = itemgetter(0)  # a window entry's t4


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

    @property
    def midpoint_ns(self) -> int:
        """(t1 + t4) / 2: the local time the exchange's offset refers to."""
        return (self.t1_ns + self.t4_ns) // 2

    def brackets(self, theta_ns: float, slack_ns: float = 0.0) -> bool:
        """True when t3 - t4 - slack <= theta <= t2 - t1 + slack (theta is physically possible)."""
        return self.t3_ns - self.t4_ns - slack_ns <= theta_ns <= self.t2_ns - self.t1_ns + slack_ns


@dataclass(frozen=True)
class OffsetEstimate:
    """theta(t) = offset_ns + drift_ppm * 1e-6 * (t - at_ns), t in OBU ns."""

    offset_ns: int  # theta = rsu_clock - obu_clock at OBU time at_ns
    uncertainty_ns: int  # bound on |offset_ns - truth| at at_ns (see the module doc)
    samples: int  # exchanges accepted so far
    drift_ppm: float = 0.0  # d theta / dt in parts per million (1 ppm = 1 us per s)
    at_ns: int = 0  # OBU time the offset refers to
    steps: int = 0  # RSU clock steps detected so far
    drift_sd_ppm: float = 0.0  # standard deviation of drift_ppm

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
class ConfirmedStep:
    """The last RSU clock step confirmed: it happened (OBU time) after ``after_ns`` (the latest t1 of
    an exchange that still agreed with the old clock) and before ``before_ns`` (the t4 of the first
    exchange that showed it); ``previous`` is the old clock's estimate when it was confirmed (it places
    what the RSU stamped before the step, extrapolated with its drift)."""

    steps: int  # steps confirmed so far, this one included
    after_ns: int
    before_ns: int
    previous: OffsetEstimate


@dataclass(frozen=True)
class _Fit:
    """The window's fit at t_ref (the newest t4); readings are relative to theta_ref (floats stay small)."""

    t_ref_ns: int
    theta_ref_ns: int
    theta_rel_ns: float  # theta(t_ref) - theta_ref
    drift: float  # ns per s
    drift_sd: float  # ns per s
    bound_ns: float  # U(t_ref)
    min_up: tuple[float, int]  # least settled detrended up reading of the current segment (ns) and its t1
    min_down: tuple[float, int]  # the same for down, and its t4
    armed: bool  # converged: enough settled samples in the current segment to judge new ones

    @property
    def width_ns(self) -> float:
        """W = m_up + m_down >= 0: the width of the offsets the segment allows, F = [-m_down, m_up]
        (detrended, relative to theta_ref; both delays >= 0), i.e. its least round trip."""
        return max(0.0, self.min_up[0] + self.min_down[0])

    def evident(self, low: float, high: float) -> bool:
        """Whether every step in [low, high] is one that no queueing explains and that the estimate's
        own uncertainty cannot hold: with the old readings, theta in F; with a step s, the new ones
        allow theta + s; when both are genuine, s = theta' - theta lies in [low - W, high + W] (low,
        high from ``step_interval``, which takes the least readings as exact). A step is confirmed
        only when that widened interval excludes 0 (the new readings and F are disjoint: the old
        readings can all be queued, the new ones too, and still not explain it) and its smallest
        size exceeds the bound U of the estimate."""
        w = self.width_ns
        least = low if low > 0.0 else -high
        return (low - w > 0.0 or high + w < 0.0) and least > self.bound_ns

    def step_interval(self, s: SyncSample, threshold_ns: float, sigmas: float) -> tuple[float, float]:
        """[low, high] of the clock steps that explain the sample (ns): x_up rises by a step, x_down falls.

        Each end is widened by the threshold and by sigmas drift sd times the time between the
        reading and the least one it is compared with (the detrending error)."""
        r_up = (s.t2_ns - s.t1_ns - self.theta_ref_ns) - self.drift * (s.t1_ns - self.t_ref_ns) / NS_PER_S
        r_down = (s.t4_ns - s.t3_ns + self.theta_ref_ns) + self.drift * (s.t4_ns - self.t_ref_ns) / NS_PER_S
        slack_up = threshold_ns + sigmas * self.drift_sd * abs(s.t1_ns - self.min_up[1]) / NS_PER_S
        slack_down = threshold_ns + sigmas * self.drift_sd * abs(s.t4_ns - self.min_down[1]) / NS_PER_S
        return -(r_down - self.min_down[0]) - slack_down, (r_up - self.min_up[0]) + slack_up


@dataclass
class _Hypothesis:
    """A suspected step: feasible sizes [low, high] (ns), its suspects and the ordinary samples since."""

    low: float
    high: float
    first_t4_ns: int
    suspects: list[tuple[int, SyncSample]] = field(default_factory=list)  # (arrival number, sample)
    since: list[tuple[SyncSample, tuple[float, float]]] = field(default_factory=list)

    evident: int = 0  # how many of its suspects showed a step beyond queueing and the bound (``_Fit.evident``)

    def overlaps(self, interval: tuple[float, float]) -> bool:
        return interval[0] <= self.high and self.low <= interval[1]


class ClockSync:
    """Offset and drift of one RSU clock from a bounded, time-limited window of exchanges.

    window: at most this many samples are kept (memory bound; 10 Hz x 60 s = 600);
    horizon_ns: samples older than this (by t4, relative to the newest) are dropped; the drift
    is fitted over the whole window, the offset from the samples of the last offset_horizon_ns;
    quantile: the lower-tail fraction taken as the envelope of each leg; bound_sigmas: drift
    standard deviations the uncertainty allows for. Samples may arrive in any order.
    silence_ns: a query (``note_request``) not answered by an exchange with a round trip of at most
    silence_ns within silence_ns means the RSU clock has not been read since: it may have stepped
    unseen, so the bound is SILENT_BOUND_NS until a prompt exchange sent after it arrives (a clock
    that stepped while the uplink buffered would otherwise be fused through with its pre-step
    bound). Without queries noted, the rule is off.

    Refits: until the fit is armed (converged) every exchange refits the window; after that
    every ``refit_every`` exchanges or ``refit_interval_ns`` of exchange time, whichever comes
    first (a confirmed step refits at once). In between, the last fit is extrapolated with its
    drift (``estimate_at``). A 600-sample fit costs ~0.6 ms: an OBU querying 8 RSUs at 10 Hz
    spent ~5 ms of every 100 ms cycle refitting for one new sample in 600.
    """

    def __init__(self, window: int = 600, *, horizon_ns: int = 60 * NS_PER_S,
                 offset_horizon_ns: int = 30 * NS_PER_S, bin_ns: int = 2 * NS_PER_S, quantile: float = 0.1,
                 drift_prior_ppm: float = 100.0, max_drift_ppm: float = 500.0, step_threshold_ns: int = 2_000_000,
                 step_confirm: int = 3, step_span: int = 10, step_armed_after: int = 30, bound_sigmas: float = 3.0,
                 refit_every: int = 5, refit_interval_ns: int = NS_PER_S, silence_ns: int = 2 * NS_PER_S):
        self.silence_ns = silence_ns
        self._unanswered: deque[int] = deque(maxlen=window)  # t1 of queries sent after the last prompt exchange's
        self.max_samples, self.horizon_ns, self.offset_horizon_ns = window, horizon_ns, offset_horizon_ns
        self.bin_ns, self.quantile = bin_ns, quantile
        self.max_drift, self.bound_sigmas = max_drift_ppm * PPM_NS_PER_S, bound_sigmas
        self.step_threshold_ns, self.step_confirm, self.step_span = step_threshold_ns, step_confirm, step_span
        self.step_armed_after = step_armed_after
        self.refit_every, self.refit_interval_ns = refit_every, refit_interval_ns
        self._samples: list[tuple[int, int, SyncSample]] = []  # (t4, clock segment, sample), by t4
        # the same window as int64 columns, kept beside it by _insert and _relabel (a fit reads them as
        # arrays through their buffers, without converting each Python int): t1, t2, t3, t4 of each
        # sample in turn, and each one's segment
        self._times = array("q")
        self._segments = array("q")
        self._segment = 0  # current clock segment (a step, or readings that disagreed with the older ones)
        self._steps = 0  # confirmed clock steps
        self._hypotheses: list[_Hypothesis] = []  # competing suspected steps (disjoint suspect clusters)
        self._last_step = (0.0, 0.0)  # feasible sizes (ns) of the last confirmed step
        self._step_first_t4_ns = 0  # arrival of its first suspect
        self.last_step: ConfirmedStep | None = None
        self._last: SyncSample | None = None
        self._total = 0
        self.outliers_rejected = 0  # suspects refuted or left unconfirmed, exchanges outside the consensus
        self._prior = (0.0, drift_prior_ppm * PPM_NS_PER_S)  # drift prior (mean, sd) in ns/s
        self._drift = self._prior  # latest drift fit (mean, sd) in ns/s
        self._inconsistent: set[SyncSample] = set()  # window samples outside the consensus (counted once)
        self._fit: _Fit | None = None  # cache, None when it must be refitted
        self._unfitted = 0  # exchanges inserted since the cached fit
        self._last_estimate: tuple | None = None  # estimate_at's last ((t, type, total, segment), answer)

    @property
    def steps_detected(self) -> int:
        """RSU clock steps confirmed so far (new segments begun without a step are not counted)."""
        return self._steps

    @property
    def converged(self) -> bool:
        """Whether the fit judges new exchanges (a clear majority and step_armed_after settled
        samples in the current segment): only then are outliers and steps recognised."""
        fit = self._current_fit()
        return fit is not None and fit.armed

    def window(self) -> list[SyncSample]:
        """The exchanges kept (every clock segment), by OBU receive time t4."""
        return [s for _, _, s in self._samples]

    def add(self, sample: SyncSample) -> bool:
        """Add an exchange (any arrival order); False (and ignored) when its timestamps are inconsistent."""
        if sample.round_trip_ns < 0 or sample.t4_ns < sample.t1_ns:
            return False
        self._total += 1
        self._last = sample
        if sample.round_trip_ns <= self.silence_ns:  # the RSU clock was read at most silence_ns after t1
            while self._unanswered and self._unanswered[0] <= sample.t1_ns:
                self._unanswered.popleft()
        self._expire_hypotheses()
        fit = self._current_fit()
        interval = None if fit is None else fit.step_interval(sample, self.step_threshold_ns, self.bound_sigmas)
        if interval is not None and not interval[0] <= 0.0 <= interval[1]:
            if self._late_before_step(sample, interval):
                return True
            if fit.armed:
                self._suspect(sample, interval, fit)
                return True
        for hyp in list(self._hypotheses):
            hyp.since.append((sample, interval))
            if sample.t1_ns > hyp.first_t4_ns and not hyp.overlaps(interval):
                self._reject(hyp)  # a genuine reply, sent after the suspect, still agrees with the old clock
        self._insert(sample, self._segment)
        return True

    def note_request(self, t1_ns: int) -> None:
        """A query was sent to the RSU at OBU time t1 (see silence_ns)."""
        if not self._unanswered or t1_ns > self._unanswered[-1]:
            self._unanswered.append(t1_ns)

    def estimate(self) -> OffsetEstimate | None:
        """The estimate at the newest OBU receive time (t4) seen."""
        return None if not self._samples else self.estimate_at(self._samples[-1][0])

    def estimate_at(self, t_obu_ns: int) -> OffsetEstimate | None:
        """The estimate extrapolated to OBU time t: theta(t) = theta0 + drift (t - t0), with U(t)."""
        key = (t_obu_ns, type(t_obu_ns), self._total, self._segment, self._unanswered[0] if self._unanswered else None)
        last = self._last_estimate  # a cycle asks for the same instant several times
        if last is not None and last[0] == key:
            # no exchange since (the same total): the same fit (only ``add`` inserts samples, arms a
            # refit or suspects a step), and no step suspected (none was when it was kept)
            return last[1]
        fit = self._current_fit()
        if fit is None:
            return None
        dt_s = (t_obu_ns - fit.t_ref_ns) / NS_PER_S
        offset = fit.theta_ref_ns + round(fit.theta_rel_ns + fit.drift * dt_s)
        bound = fit.bound_ns + self.bound_sigmas * fit.drift_sd * abs(dt_s)
        if self._hypotheses:  # while a step is suspected, the clock may have stepped by anything in its [low, high]
            bound += max(max(abs(h.low), abs(h.high)) for h in self._hypotheses)
        if self._unanswered and t_obu_ns - self._unanswered[0] > self.silence_ns:
            bound = max(bound, SILENT_BOUND_NS)  # asked and not answered promptly: a step may have gone unseen
        est = OffsetEstimate(offset, math.ceil(bound), self._total, fit.drift / PPM_NS_PER_S, t_obu_ns,
                             self._steps, fit.drift_sd / PPM_NS_PER_S)
        # while no step is suspected the answer is a function of (fit, t, total, segment) alone, and the
        # fit one of the exchanges added so far (total): kept with (t, total, segment)
        self._last_estimate = None if self._hypotheses else (key, est)
        return est

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

    # --- window -----------------------------------------------------------------------------
    def _insert(self, sample: SyncSample, segment: int) -> None:
        """Insert by t4 (replies may complete out of order); drop what is past the horizon or the window."""
        samples, t4_ns = self._samples, sample.t4_ns
        if not samples or t4_ns >= samples[-1][0]:  # the usual case: the newest (where insort puts it)
            samples.append((t4_ns, segment, sample))
            self._times.extend((sample.t1_ns, sample.t2_ns, sample.t3_ns, t4_ns))
            self._segments.append(segment)
        else:
            i = bisect_right(samples, t4_ns, key=_first)  # where insort puts it
            samples.insert(i, (t4_ns, segment, sample))
            self._times[4 * i:4 * i] = array("q", (sample.t1_ns, sample.t2_ns, sample.t3_ns, t4_ns))
            self._segments.insert(i, segment)
        newest_ns = samples[-1][0]
        cut = 0
        while cut < len(samples) and newest_ns - samples[cut][0] > self.horizon_ns:
            cut += 1
        cut = max(cut, len(samples) - self.max_samples)
        if cut:
            del samples[:cut], self._times[:4 * cut], self._segments[:cut]
        self._unfitted += 1

    def _relabel(self, moved: set[int]) -> None:
        """The samples whose id is in ``moved`` join the current segment."""
        self._samples = [(t4, self._segment if id(s) in moved else seg, s) for t4, seg, s in self._samples]
        self._segments = array("q", [seg for _, seg, _ in self._samples])

    # --- steps and outliers -----------------------------------------------------------------
    def _suspect(self, sample: SyncSample, interval: tuple[float, float], fit: _Fit) -> None:
        """Join the first hypothesis the sample agrees with, or start one (forged replies and a real
        step then make separate clusters, and the forged ones cannot break up the step's). It is
        confirmed by step_confirm suspects that are each evident against the fit they met
        (``_Fit.evident``: fits change as readings come and go, so intervals judged against
        different ones are not intersected for this)."""
        hyp = next((h for h in self._hypotheses if h.overlaps(interval)), None)
        if hyp is None:
            hyp = _Hypothesis(interval[0], interval[1], sample.t4_ns)
            self._hypotheses.append(hyp)
        hyp.low, hyp.high = max(hyp.low, interval[0]), min(hyp.high, interval[1])
        hyp.suspects.append((self._total, sample))
        hyp.evident += fit.evident(*interval)
        if hyp.evident >= self.step_confirm:
            self._new_segment(hyp, confirmed=True)

    def _late_before_step(self, sample: SyncSample, interval: tuple[float, float]) -> bool:
        """A reply stamped before the last step that arrives after it (it agrees with the previous
        segment: explained by a step of minus the last one) joins the previous segment."""
        if self._segment == 0 or sample.t1_ns >= self._step_first_t4_ns:
            return False
        low, high = self._last_step
        if not (interval[0] <= -low and -high <= interval[1]):
            return False
        self._insert(sample, self._segment - 1)
        return True

    def _expire_hypotheses(self) -> None:
        """Suspects not confirmed within step_span exchanges: rejected as outliers when their step was
        evident (too few to confirm it: forged or spurious); absorbed as ordinary exchanges when no
        step explains them (their intervals are empty: one leg below its least reading, the other
        not above its own by as much, so that least reading was queued); else the readings changed
        in a way that queueing or the estimate's bound may explain as well as a step (the readings
        before were all buffered, or the clock stepped by less than the uncertainty): the offset
        starts afresh from them (a new segment, as after a step, so that old and new readings are
        never intersected: the bound stays honest either way), but no step is counted."""
        for hyp in [h for h in self._hypotheses if h.suspects[0][0] <= self._total - self.step_span]:
            if hyp not in self._hypotheses:  # absorbed by an earlier one's new segment
                continue
            if hyp.evident:
                self._reject(hyp)
            elif hyp.low > hyp.high:  # no step explains them: more prompt than the least readings on one
                self._hypotheses.remove(hyp)  # leg, not moved on the other; those were queued, these narrow them
                for _, s in hyp.suspects:
                    self._insert(s, self._segment)
            else:
                self._new_segment(hyp, confirmed=False)

    def _reject(self, hyp: _Hypothesis) -> None:
        self.outliers_rejected += len(hyp.suspects)
        self._hypotheses.remove(hyp)

    def _new_segment(self, hyp: _Hypothesis, confirmed: bool) -> None:
        """A new clock segment starts with the hypothesis' suspects and the samples since the first of
        them that agree with it; older segments keep informing the drift. ``confirmed``: the RSU clock
        stepped (counted, ``last_step``), and the suspects of competing hypotheses are outliers;
        otherwise they join the new segment too (they disagreed with the same old readings)."""
        previous = self.estimate_at(hyp.first_t4_ns)
        self._hypotheses.remove(hyp)
        others, self._hypotheses = self._hypotheses, []
        after_ns = max((s.t1_ns for _, seg, s in self._samples if seg == self._segment and s.t1_ns < hyp.first_t4_ns),
                       default=previous.at_ns)
        moved = {id(s) for s, interval in hyp.since if hyp.overlaps(interval)}
        self._segment += 1
        self._relabel(moved)
        joining = hyp.suspects if confirmed else hyp.suspects + [x for other in others for x in other.suspects]
        for _, s in joining:
            self._insert(s, self._segment)
        self._last_step, self._step_first_t4_ns = (hyp.low, hyp.high), hyp.first_t4_ns
        if confirmed:
            self.outliers_rejected += sum(len(other.suspects) for other in others)
            self._steps += 1
            self.last_step = ConfirmedStep(self._steps, after_ns, hyp.first_t4_ns, previous)
        self._fit = None

    # --- fit --------------------------------------------------------------------------------
    def _current_fit(self) -> _Fit | None:
        fit = self._fit
        due = fit is None or self._unfitted > 0 and (
            not fit.armed or self._unfitted >= self.refit_every
            or self._samples[-1][0] - fit.t_ref_ns >= self.refit_interval_ns)
        if due and self._samples:
            self._fit, self._unfitted = self._compute_fit(), 0
        return self._fit

    def _compute_fit(self) -> _Fit:
        # copies of the columns (a view would pin the arrays' buffers: they could not grow)
        times = np.frombuffer(self._times, dtype=np.int64).reshape(-1, 4).copy()
        segments = np.frombuffer(self._segments, dtype=np.int64).copy()
        (outside, theta_ref, theta_rel, drift, sd, bound, least_up, t1, least_down, t4, armed) = fit_window(
            times, segments, *self._drift, *self._prior, self.bin_ns, self.quantile,
            self.max_drift, self.bound_sigmas, self.offset_horizon_ns / NS_PER_S, float(self.step_threshold_ns),
            self.step_span, self.step_armed_after, MIN_RESID_NS)
        self._drift = (drift, sd)
        self._count_disagreeing(outside)
        return _Fit(int(times[-1, 3]), theta_ref, theta_rel, drift, sd, bound, (least_up, t1), (least_down, t4), armed)

    def _count_disagreeing(self, outside: np.ndarray) -> None:
        """Count each exchange left out by the consensus once in outliers_rejected."""
        if self._inconsistent:  # forget what left the window
            oldest_ns = self._samples[0][0]
            self._inconsistent = {s for s in self._inconsistent if s.t4_ns >= oldest_ns}
        for i in outside.nonzero()[0]:
            if self._samples[i][2] not in self._inconsistent:
                self._inconsistent.add(self._samples[i][2])
                self.outliers_rejected += 1
