"""Pure clock-sync experiment: exchanges against a DriftingClock over random asymmetric legs.

The OBU clock is the true time base; the RSU clock is ``rsu_clock`` (offset, drift, steps), so
the truth at OBU time t is ``rsu_clock.offset_at(t)``. Each exchange k: the OBU sends at
t1 = start + k / rate; the request takes ``up`` (true ns), the RSU holds it ``hold_ns`` and the
reply takes ``down``:  t2 = rsu(t1 + up), t3 = rsu(t1 + up + hold), t4 = t1 + up + hold + down.
A leg is any ``(send_ns, rng) -> delay_ns | None`` (None: lost). Replies reach the filter in
arrival (t4) order, which need not be their send order; the estimate is scored on a grid.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from v2i.sim.clock import DriftingClock

from v2i.clock.clock_sync import NS_PER_S, ClockSync, SyncSample

NS_PER_MS = 1_000_000

DelayDraw = Callable[[int, np.random.Generator], "int | None"]  # (send time ns, rng) -> delay ns, None if lost


@dataclass(frozen=True)
class Leg:
    """One direction: delay = base_ms + median_ms * exp(sigma Z) (lognormal jitter), loss Bernoulli."""

    base_ms: float
    median_ms: float
    sigma: float
    loss: float = 0.0

    def draw_ns(self, send_ns: int, rng: np.random.Generator) -> int | None:
        """Delay of a message sent at send_ns (the time does not matter here); None when lost."""
        lost = rng.random() < self.loss
        delay_ms = self.base_ms + rng.lognormal(math.log(self.median_ms), self.sigma)
        return None if lost else round(delay_ms * NS_PER_MS)


@dataclass
class BufferedLeg:
    """A leg that buffers: a message sent inside an episode [start, end) leaves when it ends, and
    nothing overtakes an earlier message (in-order delivery, as a buffering radio bearer does).

    delay = max(end - send, 0) + leg delay, then deliver_k = max(deliver_k, deliver_{k-1});
    episodes_ns: sorted, disjoint (start_ns, end_ns) windows. Call in send order.
    """

    leg: Leg
    episodes_ns: Sequence[tuple[int, int]]
    _last_deliver_ns: int = field(default=-(2**62), repr=False)

    def draw_ns(self, send_ns: int, rng: np.random.Generator) -> int | None:
        delay_ns = self.leg.draw_ns(send_ns, rng)
        if delay_ns is None:
            return None
        release_ns = next((end for start, end in self.episodes_ns if start <= send_ns < end), send_ns)
        deliver_ns = max(release_ns + delay_ns, self._last_deliver_ns)
        self._last_deliver_ns = deliver_ns
        return deliver_ns - send_ns


def buffer_episodes(rng: np.random.Generator, start_ns: int, duration_ns: int, mean_gap_s: float,
                    episode_s: tuple[float, float]) -> list[tuple[int, int]]:
    """Buffering episodes over [start, start + duration): gaps ~ Exp(mean_gap_s), lengths ~ U(episode_s)."""
    episodes, t_ns = [], start_ns
    while True:
        t_ns += round(rng.exponential(mean_gap_s) * NS_PER_S)
        if t_ns >= start_ns + duration_ns:
            return episodes
        end_ns = t_ns + round(rng.uniform(*episode_s) * NS_PER_S)
        episodes.append((t_ns, end_ns))
        t_ns = end_ns


# LTE-V2X PC5 as in link_emulator/profiles/lte-v2x.yaml: medians 21 ms up, 22 ms down, spiky tail.
LTE_UPLINK = Leg(15.0, 6.0, 0.7, 0.02)
LTE_DOWNLINK = Leg(15.0, 7.0, 0.8, 0.03)


@dataclass(frozen=True)
class SyncRun:
    """Errors (estimate - truth, ns) on the grid t_ns (OBU time, ns since start), shape (m,)."""

    t_ns: np.ndarray
    error_ns: np.ndarray
    naive_error_ns: np.ndarray
    uncertainty_ns: np.ndarray
    steps_detected: int
    outliers_rejected: int = 0

    def _window(self, after_ns: int, until_ns: int | None) -> np.ndarray:
        return (self.t_ns >= after_ns) & (self.t_ns < (until_ns if until_ns is not None else np.inf))

    def stats_ms(self, after_ns: int = 5 * NS_PER_S, until_ns: int | None = None) -> dict[str, float]:
        """p50 / p95 / max |error| and naive p95 (ms) over after_ns <= t < until_ns."""
        keep = self._window(after_ns, until_ns)
        err, naive = np.abs(self.error_ns[keep]) / NS_PER_MS, np.abs(self.naive_error_ns[keep]) / NS_PER_MS
        return {"p50_ms": float(np.percentile(err, 50)), "p95_ms": float(np.percentile(err, 95)),
                "max_ms": float(err.max()), "naive_p95_ms": float(np.percentile(naive, 95))}

    def reconvergence_ns(self, event_ns: int, tol_ns: int = NS_PER_MS, until_ns: int | None = None) -> int:
        """Time from event_ns until |error| stays below tol_ns (up to until_ns)."""
        keep = self._window(event_ns, until_ns)
        t, bad = self.t_ns[keep], np.abs(self.error_ns[keep]) >= tol_ns
        return 0 if not bad.any() else int(t[bad][-1] - event_ns + (t[1] - t[0]))

    def unbounded(self, after_ns: int = 0, until_ns: int | None = None) -> np.ndarray:
        """Grid times (ns since start) where |error| > the stated uncertainty, shape (k,)."""
        keep = self._window(after_ns, until_ns) & (np.abs(self.error_ns) > self.uncertainty_ns)
        return self.t_ns[keep]


def exchanges(rsu_clock: DriftingClock, up: DelayDraw, down: DelayDraw, rng: np.random.Generator, start_ns: int,
              duration_ns: int, rate_hz: float = 10.0, hold_ns: int = 50_000) -> list[SyncSample]:
    """The completed exchanges, sorted by arrival t4 (lost requests or replies are absent)."""
    out = []
    for t1 in range(start_ns, start_ns + duration_ns, round(NS_PER_S / rate_hz)):
        up_ns = up(t1, rng)
        t_rx = t1 + (up_ns if up_ns is not None else 0)
        down_ns = down(t_rx + hold_ns, rng)  # both always drawn: streams independent of losses
        if up_ns is None or down_ns is None:
            continue
        out.append(SyncSample(t1, rsu_clock.local_from_true(t_rx), rsu_clock.local_from_true(t_rx + hold_ns),
                              t_rx + hold_ns + down_ns))
    return sorted(out, key=lambda s: s.t4_ns)


def forged(t1_ns: int, theta_ns: int, shift_ns: int, round_trip_ns: int, hold_ns: int = 50_000) -> SyncSample:
    """A forged reply to a request sent at t1: the RSU clock claimed to read theta + shift_ns ahead
    of the OBU's, answered with a small, symmetric round trip so that it looks precise:
    t2 = t1 + rtt / 2 + theta + shift, t3 = t2 + hold, t4 = t1 + rtt + hold."""
    t2 = t1_ns + round_trip_ns // 2 + theta_ns + shift_ns
    return SyncSample(t1_ns, t2, t2 + hold_ns, t1_ns + round_trip_ns + hold_ns)


def run_sync(rsu_clock: DriftingClock, samples: list[SyncSample], start_ns: int, duration_ns: int,
             sync: ClockSync | None = None, grid_ns: int = 20 * NS_PER_MS, rate_hz: float | None = 10.0) -> SyncRun:
    """Feed samples in arrival order and score estimate_at(t) and naive() against the truth; the
    queries (``ClockSync.note_request``) sent at ``rate_hz`` from start as ``exchanges`` sends them
    (None: none noted, the silence rule off)."""
    sync = sync if sync is not None else ClockSync()
    ts, err, naive_err, unc = [], [], [], []
    k, query_ns = 0, start_ns
    period_ns = None if rate_hz is None else round(NS_PER_S / rate_hz)
    for t in range(start_ns, start_ns + duration_ns, grid_ns):
        while period_ns is not None and query_ns <= t:
            sync.note_request(query_ns)
            query_ns += period_ns
        while k < len(samples) and samples[k].t4_ns <= t:
            sync.add(samples[k])
            k += 1
        est, naive = sync.estimate_at(t), sync.naive()
        if est is None:
            continue
        truth = rsu_clock.offset_at(t)
        ts.append(t - start_ns)
        err.append(est.offset_ns - truth)
        naive_err.append(naive.offset_ns - truth)
        unc.append(est.uncertainty_ns)
    return SyncRun(np.array(ts), np.array(err), np.array(naive_err), np.array(unc), sync.steps_detected,
                   sync.outliers_rejected)
