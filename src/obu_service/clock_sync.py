"""RSU clock offset from NTP-style four-timestamp exchanges.

t1 OBU send, t2 RSU receive, t3 RSU send, t4 OBU receive (t1, t4 OBU clock; t2, t3 RSU clock).
  offset theta = rsu_clock - obu_clock = ((t2 - t1) + (t3 - t4)) / 2
  round trip   delta = (t4 - t1) - (t3 - t2)
The error of one sample is at most delta / 2 (the unknown asymmetry of the two legs),
so the estimate is the sample with the least round trip in a sliding window (a
minimum-delay filter: queueing only ever adds delay). Its uncertainty is delta / 2.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


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


@dataclass(frozen=True)
class OffsetEstimate:
    offset_ns: int  # theta = rsu_clock - obu_clock
    uncertainty_ns: int  # half the round trip of the sample used
    samples: int


class ClockSync:
    """Minimum-delay filter over the last ``window`` samples of one RSU."""

    def __init__(self, window: int = 16):
        self._samples: deque[SyncSample] = deque(maxlen=window)
        self._total = 0

    def add(self, sample: SyncSample) -> bool:
        """Add an exchange; False (and ignored) when its timestamps are inconsistent."""
        if sample.round_trip_ns < 0 or sample.t4_ns < sample.t1_ns:
            return False
        self._samples.append(sample)
        self._total += 1
        return True

    def estimate(self) -> OffsetEstimate | None:
        if not self._samples:
            return None
        best = min(self._samples, key=lambda s: s.round_trip_ns)
        return OffsetEstimate(best.offset_ns, best.round_trip_ns // 2, self._total)

    def naive(self) -> OffsetEstimate | None:
        """The latest single exchange, as a plain NTP client without filtering would use."""
        if not self._samples:
            return None
        last = self._samples[-1]
        return OffsetEstimate(last.offset_ns, last.round_trip_ns // 2, self._total)

    def to_obu_ns(self, rsu_time_ns: int) -> int | None:
        """RSU clock reading -> OBU clock: t_obu = t_rsu - theta; None before the first exchange."""
        est = self.estimate()
        return None if est is None else rsu_time_ns - est.offset_ns
