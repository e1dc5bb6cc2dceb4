"""Clocks as the services see them: the ``Clock`` protocol, the host's clock, a node's own clock
(``LocalClock``) and the capture times of a periodic sensor. Pure code never reads a clock;
services are handed one of these (the simulator's clock models implement the same protocols).

Every reading is ``int`` nanoseconds since the Unix epoch in that clock's own time base.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np


class Clock(Protocol):
    def now_ns(self) -> int: ...


class LocalClock(Protocol):
    """A node's own clock over a true base clock: ``now_ns()`` reads it, ``local_from_true(t)``
    is its reading at true time ``t`` (ns)."""

    def now_ns(self) -> int: ...

    def local_from_true(self, true_ns: int) -> int: ...


# A node's own clock from its true base clock and time zero (true ns): how a service is handed the clock
# model it runs on (``UnskewedClock.of``, or the simulator's offset and drifting clock)
ClockModel = Callable[[Clock, int], LocalClock]


class SystemClock:
    """The host's wall clock (taken as true time in simulations on one host)."""

    def now_ns(self) -> int:
        return time.time_ns()


@dataclass(frozen=True)
class UnskewedClock:
    """A node clock that reads its base clock exactly: local(t) = t."""

    base: Clock

    @classmethod
    def of(cls, base: Clock, start_ns: int) -> "UnskewedClock":  # noqa: ARG003 (a ClockModel: time zero unused)
        return cls(base)

    def local_from_true(self, true_ns: int) -> int:
        return true_ns

    def now_ns(self) -> int:
        return self.base.now_ns()


def frame_times(rate_hz: float, duration_s: float, phase_s: float = 0.0) -> np.ndarray:
    """Capture times (K,) s of a sensor at ``rate_hz``: t_k = phase + k / rate for every t_k in [phase, duration)."""
    count = max(int(np.ceil((duration_s - phase_s) * rate_hz - 1e-9)), 0)
    return phase_s + np.arange(count) / rate_hz
