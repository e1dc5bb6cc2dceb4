"""Pure clock-sync experiment: exchanges against a DriftingClock over random asymmetric legs.

The OBU clock is the true time base; the RSU clock is ``rsu_clock`` (offset, drift, steps), so
the truth at OBU time t is ``rsu_clock.offset_at(t)``. Each exchange k: the OBU sends at
t1 = start + k / rate; the request takes ``up`` (true ns), the RSU holds it ``hold_ns`` and the
reply takes ``down``:  t2 = rsu(t1 + up), t3 = rsu(t1 + up + hold), t4 = t1 + up + hold + down.
Replies reach the filter in arrival (t4) order; the estimate is scored on a regular grid.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sim.clock import DriftingClock

from .clock_sync import NS_PER_S, ClockSync, SyncSample

NS_PER_MS = 1_000_000


@dataclass(frozen=True)
class Leg:
    """One direction: delay = base_ms + median_ms * exp(sigma Z) (lognormal jitter), loss Bernoulli."""

    base_ms: float
    median_ms: float
    sigma: float
    loss: float = 0.0

    def draw_ns(self, rng: np.random.Generator) -> int | None:
        lost = rng.random() < self.loss
        delay_ms = self.base_ms + rng.lognormal(math.log(self.median_ms), self.sigma)
        return None if lost else round(delay_ms * NS_PER_MS)


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

    def stats_ms(self, after_ns: int = 5 * NS_PER_S, until_ns: int | None = None) -> dict[str, float]:
        """p50 / p95 / max |error| and naive p95 (ms) over after_ns <= t < until_ns."""
        keep = (self.t_ns >= after_ns) & (self.t_ns < (until_ns if until_ns is not None else np.inf))
        err, naive = np.abs(self.error_ns[keep]) / NS_PER_MS, np.abs(self.naive_error_ns[keep]) / NS_PER_MS
        return {"p50_ms": float(np.percentile(err, 50)), "p95_ms": float(np.percentile(err, 95)),
                "max_ms": float(err.max()), "naive_p95_ms": float(np.percentile(naive, 95))}

    def reconvergence_ns(self, event_ns: int, tol_ns: int = NS_PER_MS, until_ns: int | None = None) -> int:
        """Time from event_ns until |error| stays below tol_ns (up to until_ns)."""
        keep = (self.t_ns >= event_ns) & (self.t_ns < (until_ns if until_ns is not None else np.inf))
        t, bad = self.t_ns[keep], np.abs(self.error_ns[keep]) >= tol_ns
        return 0 if not bad.any() else int(t[bad][-1] - event_ns + (t[1] - t[0]))


def exchanges(rsu_clock: DriftingClock, up: Callable[[np.random.Generator], int | None],
              down: Callable[[np.random.Generator], int | None], rng: np.random.Generator, start_ns: int,
              duration_ns: int, rate_hz: float = 10.0, hold_ns: int = 50_000) -> list[SyncSample]:
    """The completed exchanges, sorted by arrival t4 (lost requests or replies are absent)."""
    out = []
    for t1 in range(start_ns, start_ns + duration_ns, round(NS_PER_S / rate_hz)):
        up_ns, down_ns = up(rng), down(rng)  # both always drawn: streams independent of losses
        if up_ns is None or down_ns is None:
            continue
        t_rx = t1 + up_ns
        out.append(SyncSample(t1, rsu_clock.local_from_true(t_rx), rsu_clock.local_from_true(t_rx + hold_ns),
                              t_rx + hold_ns + down_ns))
    return sorted(out, key=lambda s: s.t4_ns)


def run_sync(rsu_clock: DriftingClock, samples: list[SyncSample], start_ns: int, duration_ns: int,
             sync: ClockSync | None = None, grid_ns: int = 20 * NS_PER_MS) -> SyncRun:
    """Feed samples in arrival order and score estimate_at(t) and naive() against the truth."""
    sync = sync if sync is not None else ClockSync()
    ts, err, naive_err, unc = [], [], [], []
    k = 0
    for t in range(start_ns, start_ns + duration_ns, grid_ns):
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
    return SyncRun(np.array(ts), np.array(err), np.array(naive_err), np.array(unc), sync.steps_detected)
