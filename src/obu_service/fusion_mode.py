"""Fusion modes (IAAD, Liu et al.) and the policy that picks one per cycle. Pure.

- ``intra``: fuse the RSU frame of this cycle's sensing slot (the newest RSU capture at or
  before the own LiDAR capture), waiting for it at most until the cycle's fusion deadline;
- ``inter``: fuse the newest buffered RSU frame (age up to ~0.6 s), compensated to the cycle;
- ``planning``: track with own data only and hand the RSU's 5 s predicted paths to the
  planner-facing output;
- ``vehicle-only``: own data only.

The list is ordered from most to least accurate. ``adaptive`` picks, each cycle, the most
accurate mode that is feasible (see ``Feasible``), with hysteresis on the way back up: a
better level must have been feasible for ``hysteresis_cycles`` cycles in a row before it
is chosen again, so a flaky link does not flap the vehicle between its tracker and its
planner. Going down is immediate. Intra and inter are one level (both feed the tracker),
so the policy moves between them every cycle as the intra wait budget allows.

At fusion time the planned mode may turn out unavailable (the awaited frame did not come):
``adaptive`` then falls back to the next available mode within the same cycle; a fixed
mode falls back to ``vehicle-only`` (and that cycle counts as an RSU deadline miss).
"""

from __future__ import annotations

from dataclasses import dataclass

MODES = ("intra", "inter", "planning", "vehicle-only")  # most to least accurate
TRACKING_MODES = ("intra", "inter")  # the modes that feed RSU data to the tracker
FUSION_MODES = ("adaptive", *MODES)


@dataclass(frozen=True)
class Feasible:
    """Which RSU-using modes can deliver this cycle (vehicle-only always can)."""

    intra: bool = False
    inter: bool = False
    planning: bool = False

    def __contains__(self, mode: str) -> bool:
        return mode == "vehicle-only" or bool(getattr(self, mode))


class ModePolicy:
    """Plans a mode per cycle (``select``) and resolves it at fusion time (``resolve``)."""

    def __init__(self, fusion_mode: str = "adaptive", hysteresis_cycles: int = 3):
        if fusion_mode not in FUSION_MODES:
            raise ValueError(f"fusion mode must be one of {FUSION_MODES}, got {fusion_mode!r}")
        if hysteresis_cycles < 1:
            raise ValueError(f"hysteresis_cycles must be >= 1, got {hysteresis_cycles}")
        self.fusion_mode = fusion_mode
        self.hysteresis_cycles = hysteresis_cycles
        self._level: int | None = None  # none yet: the first cycle takes the best feasible level
        self._streak = [0, 0, 0]  # consecutive feasible cycles per level

    def select(self, feasible: Feasible) -> str:
        """The mode to plan this cycle for, given what is feasible now."""
        if self.fusion_mode != "adaptive":
            return self.fusion_mode
        level_ok = [feasible.intra or feasible.inter, feasible.planning, True]
        self._streak = [s + 1 if ok else 0 for s, ok in zip(self._streak, level_ok)]
        best = level_ok.index(True)
        if self._level is None or best > self._level or not level_ok[self._level]:
            self._level = best  # down (or forced off an infeasible level) at once
        else:
            # up only to a level that has been feasible long enough
            stable = [lv for lv in range(self._level) if self._streak[lv] >= self.hysteresis_cycles]
            self._level = min(stable, default=self._level)
        if self._level == 0:
            return "intra" if feasible.intra else "inter"
        return MODES[self._level + 1]

    def resolve(self, planned: str, available: Feasible) -> str:
        """The mode actually used at fusion time, given the data that is there now."""
        if planned in available:
            return planned
        if self.fusion_mode != "adaptive":
            return "vehicle-only"
        return next(m for m in MODES[MODES.index(planned):] if m in available)
