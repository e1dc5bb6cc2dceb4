"""Per-stage latency of one service process: a thread-safe recorder of durations (seconds).

A service node keeps one ``StageLatency`` (``node.latency``) and observes each stage of each
message as it passes (RSU ``detect``, ``encode``, ``put``; link ``relay_hold``, ``relay_late``;
OBU ``rsu_to_obu``, ``queue``, ``decode``, ``fuse``, ``publish``; see the services' docstrings).

Two views of the same observations:

- ``histogram(stage)``: exact over every valid observation since start, cumulative counts per
  ``BUCKETS_S`` upper bound (Prometheus ``le`` semantics: count of values <= bound) plus +Inf
  last, their sum (s) and count; what ``/metrics`` exports.
- ``summary_ms()``: p50 / p95 / p99 in ms over a bounded ring of the latest ``RING_SIZE``
  observations per stage (``numpy.percentile``, linear interpolation: exact for those samples,
  not estimated from buckets), and the whole-run count; what the metrics messages carry.

NaN, infinite and negative durations are not recorded; they are counted per stage in
``invalid()`` (a negative one means a clock stepped or two clocks disagree: worth seeing).
Cost per observation: a lock, a bisect over ~21 bounds and a deque append (~0.4 us here);
``summary_ms`` over full rings costs ~0.08 ms per stage, so a service that publishes metrics
every cycle takes it through ``PeriodicSummary`` (at most once a second).
"""

from __future__ import annotations

import bisect
import math
import threading
from collections import Counter, deque

import numpy as np

# Prometheus-style upper bounds (s): 10^(k/4) for k = -16 .. 4, i.e. 0.1 ms .. 10 s, 4 per decade
BUCKETS_S: tuple[float, ...] = tuple(float(f"{10 ** (k / 4):.2g}") for k in range(-16, 5))
RING_SIZE = 4096  # latest observations per stage kept for the quantiles
MAX_STAGES = 32  # distinct stage names; more are refused (counted under TOO_MANY_STAGES)
TOO_MANY_STAGES = "too_many_stages"
QUANTILES = (("p50", 50.0), ("p95", 95.0), ("p99", 99.0))


class _Stage:
    """One stage's buckets (non-cumulative counts, +Inf last), sum, count and ring."""

    __slots__ = ("counts", "sum_s", "count", "ring")

    def __init__(self, ring_size: int) -> None:
        self.counts = [0] * (len(BUCKETS_S) + 1)
        self.sum_s = 0.0
        self.count = 0
        self.ring: deque[float] = deque(maxlen=ring_size)


class StageLatency:
    """Durations by stage name; every method is thread-safe (one lock)."""

    def __init__(self, ring_size: int = RING_SIZE) -> None:
        if ring_size < 1:
            raise ValueError(f"ring_size must be >= 1, got {ring_size}")
        self._ring_size = ring_size
        self._stages: dict[str, _Stage] = {}
        self._invalid: Counter[str] = Counter()
        self._lock = threading.Lock()

    def observe(self, stage: str, seconds: float) -> None:
        """Record one duration (s); NaN, infinite or negative ones are only counted in ``invalid``."""
        valid = seconds >= 0.0 and math.isfinite(seconds)  # NaN compares False
        with self._lock:
            entry = self._stages.get(stage)
            if entry is None:
                if len(self._stages) >= MAX_STAGES:
                    self._invalid[TOO_MANY_STAGES] += 1
                    return
                entry = self._stages[stage] = _Stage(self._ring_size)
            if not valid:
                self._invalid[stage] += 1
                return
            # bisect_left: the first bound >= seconds, so a value equal to a bound counts in it (le)
            entry.counts[bisect.bisect_left(BUCKETS_S, seconds)] += 1
            entry.sum_s += seconds
            entry.count += 1
            entry.ring.append(seconds)

    def observe_ns(self, stage: str, start_ns: int, end_ns: int) -> None:
        """Record ``end_ns - start_ns`` (two readings of one clock, ns) as seconds."""
        self.observe(stage, (end_ns - start_ns) * 1e-9)

    def stages(self) -> list[str]:
        """Stage names seen so far, in first-seen order."""
        with self._lock:
            return list(self._stages)

    def histogram(self, stage: str) -> tuple[list[int], float, int]:
        """Cumulative counts per ``BUCKETS_S`` bound with +Inf last (len(BUCKETS_S) + 1), sum (s), count.

        An unknown stage gives zeros.
        """
        with self._lock:
            entry = self._stages.get(stage)
            if entry is None:
                return [0] * (len(BUCKETS_S) + 1), 0.0, 0
            counts, sum_s, count = list(entry.counts), entry.sum_s, entry.count
        cumulative = np.cumsum(counts).tolist()
        return cumulative, sum_s, count

    def summary_ms(self) -> dict[str, dict[str, float | int]]:
        """``{stage: {"count", "p50", "p95", "p99"}}``: count since start, quantiles (ms, rounded to
        1 us) over the latest ``RING_SIZE`` observations. Stages with no valid observation are left out."""
        with self._lock:
            rings = {name: (entry.count, np.fromiter(entry.ring, float, len(entry.ring)))
                     for name, entry in self._stages.items() if entry.count}
        out: dict[str, dict[str, float | int]] = {}
        for name, (count, samples_s) in rings.items():
            values_ms = np.percentile(samples_s, [q for _, q in QUANTILES]) * 1e3
            out[name] = {"count": count, **{label: round(float(v), 3) for (label, _), v in zip(QUANTILES, values_ms)}}
        return out

    def invalid(self) -> dict[str, int]:
        """Refused observations by stage (NaN, infinite, negative), and ``TOO_MANY_STAGES``."""
        with self._lock:
            return dict(self._invalid)


class PeriodicSummary:
    """``latency.summary_ms()`` recomputed at most once per ``period_ns`` (clock ns given by the
    caller); the previous one in between. For metrics published every cycle."""

    def __init__(self, latency: StageLatency, period_ns: int = 1_000_000_000) -> None:
        self._latency = latency
        self._period_ns = period_ns
        self._at_ns: int | None = None
        self._summary: dict[str, dict[str, float | int]] = {}

    def get(self, now_ns: int) -> dict[str, dict[str, float | int]]:
        if self._at_ns is None or now_ns - self._at_ns >= self._period_ns or now_ns < self._at_ns:
            self._summary, self._at_ns = self._latency.summary_ms(), now_ns
        return self._summary
