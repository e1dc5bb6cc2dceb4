"""Per-RSU link monitor over a sliding time window (pure: times are arguments, OBU clock ns).

For each received object list the caller passes its sequence number and its RSU capture and
publish times already placed in OBU time (t_obu = t_rsu - theta(t), from the clock estimate),
and the OBU receive time. Over the last ``window_ns`` of arrivals the monitor reports

- one-way delay    d = receive - publish          (network + queueing; jitter is taken on it)
- latency          l = receive - capture          (RSU processing + network: the age of the frame
                                                    on arrival, what a fusion policy waits for)
- jitter           J = mean |d_i - d_(i-1)| over consecutive arrivals (the quantity RFC 3550's
                   running estimate J += (|D| - J) / 16 tracks, here as a window mean)
- loss             from sequence gaps: per sequence epoch, expected = max - min + 1 of the
                   sequence numbers seen in the window, lost = expected - distinct seen;
                   late (reordered) arrivals fill their gap, duplicates are counted and ignored.
                   A backward jump of more than ``max_misorder`` or a forward jump of more than
                   ``max_dropout`` is an RSU restart (RFC 3550 A.1): a new epoch begins.
                   A list whose number is no message counter (a CPM's, made from its time: the
                   standard carries no counter) counts for delay and latency, not for loss: with
                   only such lists the loss is unknown (None), not the gaps between timestamps.
- data age at fusion, recorded once per OBU cycle with ``on_fusion``.

``arrival_probability(W)`` answers "a frame captured at t: is it here by t + W?":
  P = (1 - loss) * P(l <= W | arrived), the empirical CDF of the windowed latencies.
Memory is bounded: at most ``max_records`` arrivals and cycles are kept.
"""

from __future__ import annotations

from bisect import bisect_left, bisect_right, insort
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

NS_PER_MS = 1_000_000


@dataclass(frozen=True)
class Arrival:
    receive_ns: int  # OBU clock
    seq: int
    epoch: int  # sequence epoch (a new one after each RSU restart)
    latency_ms: float | None  # receive - capture (OBU time)
    delay_ms: float | None  # receive - publish (OBU time)


UNCOUNTED_EPOCH = -1  # the epoch of arrivals whose number is no message counter (epochs count up from 0)


def gap_loss(seqs: Iterable[int], epochs: Iterable[int]) -> tuple[int, int]:
    """(lost, expected) over distinct (epoch, seq) pairs: expected = sum over epochs of max - min + 1.

    (Sets, not np.unique: a window holds tens of arrivals and the OBU asks at every cycle.)"""
    by_epoch: dict[int, set[int]] = {}
    for epoch, seq in zip(epochs, seqs):
        by_epoch.setdefault(int(epoch), set()).add(int(seq))
    lost = expected = 0
    for distinct in by_epoch.values():
        span = max(distinct) - min(distinct) + 1
        expected += span
        lost += span - len(distinct)
    return lost, expected


def mean_abs_diff(values: np.ndarray) -> float | None:
    """J = mean |v_i - v_(i-1)| of consecutive values; None with fewer than two."""
    return float(np.mean(np.abs(np.diff(values)))) if len(values) >= 2 else None


def quantile_or_none(values: np.ndarray, q: float) -> float | None:
    return float(np.quantile(values, q)) if len(values) else None


class LinkMonitor:
    """Sliding-window link statistics of one RSU (see module doc)."""

    def __init__(self, window_ns: int = 10_000_000_000, max_records: int = 4096, max_misorder: int = 100,
                 max_dropout: int = 3000):
        self.window_ns, self.max_records = window_ns, max_records
        self.max_misorder, self.max_dropout = max_misorder, max_dropout
        self._arrivals: deque[Arrival] = deque()
        self._seen: set[tuple[int, int]] = set()  # (epoch, seq) of the arrivals in the window
        self._ages: deque[tuple[int, float]] = deque()  # (cycle OBU ns, data age ms)
        self._epoch = 0
        self._highest: int | None = None  # highest seq of the current epoch
        self._lowest: int | None = None  # lowest seq of the current epoch
        self._sent_before = 0  # lists numbered in the epochs before the current one (sent_total)
        self.duplicates_total = self.reordered_total = self.restarts_total = 0
        self._last_receive_ns: int | None = None
        # the window's latencies (ms) sorted, and each epoch's sequence numbers sorted, kept as arrivals
        # come and go: the OBU asks for arrival_probability every cycle (O(log n), not a pass over the window)
        self._latencies: list[float] = []
        self._epoch_seqs: dict[int, list[int]] = {}

    # --- input -----------------------------------------------------------------------------
    def on_message(self, seq: int, capture_obu_ns: int | None, publish_obu_ns: int | None,
                   receive_obu_ns: int, counted: bool = True) -> bool:
        """Record an arrival; False for a duplicate (same epoch and seq still in the window).

        capture/publish are the RSU's stamps in OBU time (None while the clock is unknown: the
        arrival then counts for loss only). ``counted``: ``seq`` is a message counter; False for a
        number that only tells lists apart (``UNCOUNTED_EPOCH``: no loss, no restarts from it).
        """
        self.expire(receive_obu_ns)
        self._last_receive_ns = receive_obu_ns
        if counted:
            self._track_sequence(seq)  # first: a restart starts the new epoch with this arrival
        epoch = self._epoch if counted else UNCOUNTED_EPOCH
        if (epoch, seq) in self._seen:
            self.duplicates_total += 1
            return False
        latency = None if capture_obu_ns is None else (receive_obu_ns - capture_obu_ns) / NS_PER_MS
        delay = None if publish_obu_ns is None else (receive_obu_ns - publish_obu_ns) / NS_PER_MS
        self._arrivals.append(Arrival(receive_obu_ns, seq, epoch, latency, delay))
        self._seen.add((epoch, seq))
        if counted:
            insort(self._epoch_seqs.setdefault(epoch, []), seq)
        if latency is not None:
            insort(self._latencies, latency)
        while len(self._arrivals) > self.max_records:
            self._drop_oldest()
        return True

    def note_sequence(self, seq: int) -> None:
        """A counted list's number alone (no arrival recorded: its times cannot be placed yet), for the
        sequence epochs and ``sent_total``."""
        self._track_sequence(seq)

    def on_fusion(self, t_obu_ns: int, age_ms: float | None) -> None:
        """Record the age of the RSU data used at a fusion cycle (None: no RSU data used)."""
        self.expire(t_obu_ns)
        if age_ms is not None:
            self._ages.append((t_obu_ns, float(age_ms)))
            while len(self._ages) > self.max_records:
                self._ages.popleft()

    def expire(self, now_obu_ns: int) -> None:
        """Forget arrivals and cycles older than the window."""
        horizon = now_obu_ns - self.window_ns
        while self._arrivals and self._arrivals[0].receive_ns < horizon:
            self._drop_oldest()
        while self._ages and self._ages[0][0] < horizon:
            self._ages.popleft()

    # --- statistics ------------------------------------------------------------------------
    def delays_ms(self) -> np.ndarray:
        """One-way delays (receive - publish) in arrival order, shape (n,)."""
        return np.array([a.delay_ms for a in self._arrivals if a.delay_ms is not None], dtype=float)

    def latencies_ms(self) -> np.ndarray:
        """Latencies (receive - capture) in arrival order, shape (n,)."""
        return np.array([a.latency_ms for a in self._arrivals if a.latency_ms is not None], dtype=float)

    def delay_quantile_ms(self, q: float) -> float | None:
        return quantile_or_none(self.delays_ms(), q)

    def latency_quantile_ms(self, q: float) -> float | None:
        return quantile_or_none(self.latencies_ms(), q)

    def jitter_ms(self) -> float | None:
        return mean_abs_diff(self.delays_ms())

    def loss(self) -> tuple[int, int]:
        """(lost, expected) messages in the window, from sequence gaps: ``gap_loss`` of the arrivals,
        from each epoch's sorted sequence numbers (the window holds each (epoch, seq) once)."""
        lost = expected = 0
        for seqs in self._epoch_seqs.values():
            span = seqs[-1] - seqs[0] + 1
            expected += span
            lost += span - len(seqs)
        return lost, expected

    def sent_total(self) -> int | None:
        """Lists the RSU numbered since the first counted arrival: per epoch, highest - lowest + 1 of the
        sequence numbers seen (whatever arrived or not); None before any counted arrival."""
        if self._highest is None:
            return None
        return self._sent_before + self._highest - self._lowest + 1

    def loss_ratio(self) -> float | None:
        lost, expected = self.loss()
        return lost / expected if expected else None

    def arrival_probability(self, within_ms: float) -> float:
        """P(a frame arrives within ``within_ms`` of its capture) = (1 - loss) * P(l <= W);
        0.0 with no latency measured yet (nothing known: do not count on it)."""
        latencies = self._latencies
        if not latencies:
            return 0.0
        on_time = float(bisect_right(latencies, within_ms)) / len(latencies)  # #{l <= W} / n
        return (1.0 - (self.loss_ratio() or 0.0)) * on_time

    def summary(self, now_obu_ns: int | None = None) -> dict[str, float | int | None]:
        """Window statistics for metrics (ms, ratios, counts); None where nothing was measured."""
        if now_obu_ns is not None:
            self.expire(now_obu_ns)
        delays, latencies = self.delays_ms(), self.latencies_ms()
        ages = np.array([age for _, age in self._ages], dtype=float)
        lost, expected = self.loss()
        out: dict[str, float | int | None] = {
            "messages": len(self._arrivals), "lost": lost, "loss_ratio": lost / expected if expected else None,
            "duplicates_total": self.duplicates_total, "reordered_total": self.reordered_total,
            "restarts_total": self.restarts_total, "jitter_ms": mean_abs_diff(delays),
            "fusion_age_mean_ms": float(ages.mean()) if len(ages) else None,
            "fusion_age_p95_ms": quantile_or_none(ages, 0.95),
            "fusion_age_max_ms": float(ages.max()) if len(ages) else None,
            "since_last_ms": None if now_obu_ns is None or self._last_receive_ns is None
            else (now_obu_ns - self._last_receive_ns) / NS_PER_MS,
        }
        for name, values in (("delay", delays), ("latency", latencies)):
            for pct in (50, 95, 99):
                out[f"{name}_p{pct}_ms"] = quantile_or_none(values, pct / 100)
        return out

    # --- internals -------------------------------------------------------------------------
    def _track_sequence(self, seq: int) -> None:
        """Advance the highest seq, count reordering, start a new epoch on a restart jump."""
        if self._highest is None:
            self._highest = self._lowest = seq
            return
        jump = seq - self._highest
        if jump < -self.max_misorder or jump > self.max_dropout:  # RSU restarted (or renumbered)
            self._sent_before = self.sent_total()
            self._epoch += 1
            self.restarts_total += 1
            self._highest = self._lowest = seq
        elif jump > 0:
            self._highest = seq
        elif (self._epoch, seq) not in self._seen:
            self.reordered_total += 1  # late, but new: it fills its gap
        self._lowest = min(self._lowest, seq)

    def _drop_oldest(self) -> None:
        old = self._arrivals.popleft()
        self._seen.discard((old.epoch, old.seq))
        if old.epoch != UNCOUNTED_EPOCH:
            seqs = self._epoch_seqs[old.epoch]
            del seqs[bisect_left(seqs, old.seq)]
            if not seqs:
                del self._epoch_seqs[old.epoch]
        if old.latency_ms is not None:
            del self._latencies[bisect_left(self._latencies, old.latency_ms)]
