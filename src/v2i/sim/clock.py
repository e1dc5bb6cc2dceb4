"""Simulated clock models: the offline runner's clock, and a node clock that is offset, drifts and
steps (``DriftingClock``; the RSU's in a run: ``rsu_clock``). They implement ``v2i.core.clock``'s
``Clock`` and ``LocalClock``; ``Clock`` and ``SystemClock`` are re-exported from there.

Every reading is ``int`` nanoseconds since the Unix epoch in that clock's own time base.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from v2i.core.clock import Clock, SystemClock

__all__ = ["Clock", "ClockStep", "DriftingClock", "SimClock", "SystemClock", "rsu_clock"]


@dataclass
class SimClock:
    """A clock the offline runner sets; reads return the simulated true time."""

    t_ns: int = 0

    def now_ns(self) -> int:
        return self.t_ns


@dataclass(frozen=True)
class ClockStep:
    at_true_ns: int  # true time at which the step happens
    step_ns: int  # added to the local reading from then on


@dataclass(frozen=True)
class DriftingClock:
    """A node clock that is offset, drifts and may step relative to a true base clock.

    local(t) = t + offset_ns + drift_ppm * 1e-6 * (t - ref_ns) + sum(step_ns for steps with t >= at)
    """

    base: Clock
    offset_ns: int = 0
    drift_ppm: float = 0.0
    ref_ns: int = 0
    steps: tuple[ClockStep, ...] = field(default=())

    def local_from_true(self, true_ns: int) -> int:
        drift_ns = round(self.drift_ppm * 1e-6 * (true_ns - self.ref_ns))
        steps_ns = sum(s.step_ns for s in self.steps if true_ns >= s.at_true_ns)
        return true_ns + self.offset_ns + drift_ns + steps_ns

    def offset_at(self, true_ns: int) -> int:
        """theta(t) = local(t) - t: the truth a clock-sync estimator is scored against."""
        return self.local_from_true(true_ns) - true_ns

    def now_ns(self) -> int:
        return self.local_from_true(self.base.now_ns())


def rsu_clock(config, base: Clock, start_ns: int) -> DriftingClock:
    """The RSU's own clock over the true ``base`` clock, as an ``RsuConfig`` sets it (``clock_offset_ms``,
    ``clock_drift_ppm``, ``clock_step_ms`` at ``clock_step_at_s`` of the run): offset, drifting, maybe stepping."""
    steps = ()
    if config.clock_step_ms and config.clock_step_at_s is not None:
        steps = (ClockStep(start_ns + round(config.clock_step_at_s * 1e9), round(config.clock_step_ms * 1e6)),)
    return DriftingClock(base, offset_ns=round(config.clock_offset_ms * 1e6), drift_ppm=config.clock_drift_ppm,
                         ref_ns=start_ns, steps=steps)
