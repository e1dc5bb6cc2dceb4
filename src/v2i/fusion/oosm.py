"""Out-of-sequence measurements by re-filtering (a wrapper around ``Tracker``).

An RSU list captured at t arrives after own LiDAR frames of later times. The wrapper keeps
the measurement batches (t_s, dets, source_mask) of the last ``window_s`` seconds, in time
order, each with a snapshot of the filter taken just before it was applied (the oldest one
is the snapshot at the start of the window). A batch older than the newest applied one is
inserted in time order; the filter returns to the snapshot before its position and every
later batch is re-applied in time order. This equals restoring the window-start snapshot
and re-applying the whole window (the earlier batches would reproduce the same snapshot),
at a fraction of the work. Batches older than newest - ``window_s`` are dropped and counted.

Applying a batch at time t: when t is later than the filter time t0, ``prune(t0)`` first
(the cycle at t0 is complete), then ``predict(t)`` and ``update(dets, t, source_mask)``.
Batches with equal times keep their arrival order. So the result equals a plain Tracker fed
the same batches in time order as predict(t), update(...) for each batch at t, prune(t).
Track ids of tracks spawned after a late batch's time may change when it is re-filtered.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

from v2i.core.objects import ObjectArray
from v2i.fusion.tracking import Tracker, TrackerSnapshot


@dataclass(frozen=True)
class _Batch:
    t_s: float
    dets: ObjectArray
    source_mask: int
    estimates: bool  # the batch holds another tracker's estimates (see Tracker.update)
    before: TrackerSnapshot  # the filter just before this batch was applied


class OosmTracker:
    """A Tracker that accepts measurement batches in any order within ``window_s`` seconds."""

    def __init__(self, tracker: Tracker, window_s: float = 0.5):
        if window_s < 0:
            raise ValueError(f"window_s must be >= 0, got {window_s}")
        self.tracker = tracker
        self.window_s = window_s
        self._history: list[_Batch] = []
        self.dropped_batches = 0
        self.dropped_measurements = 0
        self.refilter_runs = 0

    @property
    def newest_s(self) -> float | None:
        """Time of the newest applied batch (None before the first)."""
        return self._history[-1].t_s if self._history else self.tracker.time_s

    def update(self, dets: ObjectArray, t_s: float, source_mask: int = 0, estimates: bool = False) -> None:
        """Apply a batch at its own time t_s (seconds, the tracker's time origin), re-filtering if
        late; ``estimates`` as in ``Tracker.update``."""
        pos = bisect.bisect_right([b.t_s for b in self._history], t_s)
        if self._too_old(t_s, pos):
            self.dropped_batches += 1
            self.dropped_measurements += len(dets)
            return
        if pos == len(self._history):
            self._history.append(self._apply(t_s, dets, source_mask, estimates))
        else:
            self._refilter(pos, t_s, dets, source_mask, estimates)
        self._trim()

    def tracks(self, t_s: float) -> ObjectArray:
        """Confirmed and coasting tracks predicted to t_s on a copy; the filter is not disturbed."""
        return self.tracker.tracks(t_s)

    def _too_old(self, t_s: float, pos: int) -> bool:
        """Older than the window, or older than the filter state it would be applied to."""
        newest = self.newest_s
        base_s = self._history[pos].before.t_s if pos < len(self._history) else self.tracker.time_s
        return (newest is not None and t_s < newest - self.window_s) or (base_s is not None and t_s < base_s)

    def _apply(self, t_s: float, dets: ObjectArray, source_mask: int, estimates: bool) -> _Batch:
        before = self.tracker.snapshot()
        t0 = self.tracker.time_s
        if t0 is not None and t_s > t0:
            self.tracker.prune(t0)  # the cycle at t0 is complete
        self.tracker.predict(t_s)
        self.tracker.update(dets, t_s, source_mask, estimates)
        return _Batch(t_s, dets, source_mask, estimates, before)

    def _refilter(self, pos: int, t_s: float, dets: ObjectArray, source_mask: int, estimates: bool) -> None:
        later = self._history[pos:]
        self.tracker.restore(later[0].before)
        del self._history[pos:]
        self._history.append(self._apply(t_s, dets, source_mask, estimates))
        for batch in later:
            self._history.append(self._apply(batch.t_s, batch.dets, batch.source_mask, batch.estimates))
        self.refilter_runs += 1

    def _trim(self) -> None:
        horizon_s = self._history[-1].t_s - self.window_s
        drop = 0
        while drop < len(self._history) and self._history[drop].t_s < horizon_s:
            drop += 1
        del self._history[:drop]
