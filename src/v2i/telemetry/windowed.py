"""Ratios over the last N seconds from cumulative counters (pure; times are arguments).

A service publishes running totals (``cycles``, ``output_deadline_misses``, ...). The ratio over
a window is the ratio of the counters' increments across it:

    ratio_W = (misses(t_now) - misses(t_base)) / (cycles(t_now) - cycles(t_base))

with ``t_base`` the newest kept point at or before ``t_now - W`` (the oldest point while less
than ``W`` has been seen). Points closer than ``W / MAX_POINTS`` to the previous kept one replace
the newest instead of adding one, so memory is bounded however fast the counters arrive. A
counter that goes down (the service restarted) starts the history again.
"""

from __future__ import annotations

from collections import deque

MAX_POINTS = 200  # kept points per window (10 s window: one per 50 ms at most)


class WindowedCounters:
    """The history of a few named cumulative counters, to difference over a time window.

    ``window_ns``: the window length (ns). ``add(t_ns, counters)`` with non-decreasing ``t_ns``
    (receive times); ``delta(now)`` the increments over the window ending at the newest point.
    """

    def __init__(self, window_ns: int, max_points: int = MAX_POINTS):
        if window_ns <= 0 or max_points < 2:
            raise ValueError("window_ns must be > 0 and max_points >= 2")
        self.window_ns = window_ns
        self._spacing_ns = window_ns // max_points
        self._points: deque[tuple[int, dict[str, int]]] = deque(maxlen=max_points + 2)
        self.resets = 0  # times a counter went down (a restarted service)

    def add(self, t_ns: int, counters: dict[str, int]) -> None:
        """Record the totals ``counters`` as of ``t_ns``; a decrease of any of them restarts the history."""
        if self._points:
            last_t, last = self._points[-1]
            t_ns = max(t_ns, last_t)  # a receive clock that stepped back: keep the order, not the step
            if any(counters.get(k, 0) < v for k, v in last.items()):
                self._points.clear()
                self.resets += 1
        point = (t_ns, dict(counters))
        if len(self._points) >= 2 and t_ns - self._points[-2][0] < self._spacing_ns:
            self._points[-1] = point  # too close to the previous kept point: the newest replaces
        else:
            self._points.append(point)
        self._trim()

    def _trim(self) -> None:
        """Drop points older than the newest one at or before ``newest - window`` (the base)."""
        cutoff = self._points[-1][0] - self.window_ns
        while len(self._points) >= 2 and self._points[1][0] <= cutoff:
            self._points.popleft()

    def delta(self) -> tuple[float, dict[str, int]]:
        """``(span_s, increments)`` across the window: the seconds between the base point and the
        newest, and each counter's increase over them (``(0.0, {})`` before any point)."""
        if not self._points:
            return 0.0, {}
        (t0, base), (t1, newest) = self._points[0], self._points[-1]
        return (t1 - t0) * 1e-9, {k: v - base.get(k, 0) for k, v in newest.items()}

    def __len__(self) -> int:
        return len(self._points)


def ratio(numerator: int, denominator: int) -> float | None:
    """``numerator / denominator`` rounded to 4 places, None when the denominator is 0."""
    return round(numerator / denominator, 4) if denominator > 0 else None


def shares(counts: dict[str, int]) -> dict[str, float]:
    """Each key's share of the total (rounded to 4 places), in decreasing order; {} when empty."""
    total = sum(counts.values())
    if total <= 0:
        return {}
    return {k: round(v / total, 4) for k, v in sorted(counts.items(), key=lambda kv: -kv[1]) if v > 0}
