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

An RSU's data is offered to a mode only while its clock is known well enough for it
(``obu_service.mode_inputs``: tracking modes up to ``max_clock_uncertainty_ms``, planning up
to ``planning_max_clock_uncertainty_ms``). Each output says why its mode is the one it is
(``FusedObjectList.mode_reason``, ``mode_reason`` below), the first that applies of:

- ``best``: the most accurate mode the configuration allows ran (adaptive: intra or inter;
  a fixed mode: that mode; ``--fusion vehicle-only``: vehicle-only);
- ``hysteresis``: a better level is feasible, but adaptive has not seen it feasible for
  ``hysteresis_cycles`` cycles in a row yet (after a ``clock_uncertainty`` fallback that a
  confirmed clock step explains, adaptive climbs back at once: ``climb_at_once``);
- ``clock_uncertainty``: a better level was not feasible because the data some RSU had for
  it was withheld for its clock uncertainty;
- ``intra_frame_late``: the fixed intra mode waited for its slot's frame and it did not come
  by the fusion deadline;
- ``not_synced``: an RSU's data is there but its clock is not synchronised yet;
- ``no_rsu_data``: no RSU data for a better mode (none heard, or too old).
"""

from __future__ import annotations

from dataclasses import dataclass

MODES = ("intra", "inter", "planning", "vehicle-only")  # most to least accurate
TRACKING_MODES = ("intra", "inter")  # the modes that feed RSU data to the tracker
FUSION_MODES = ("adaptive", *MODES)
MODE_REASONS = ("best", "hysteresis", "clock_uncertainty", "intra_frame_late", "not_synced", "no_rsu_data")


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

    def climb_at_once(self) -> None:
        """Let the next cycle climb to any level feasible then without waiting ``hysteresis_cycles``:
        after a fallback the link did not cause (an RSU's clock was uncertain while a step was
        suspected; the step is now confirmed and its data placed again)."""
        self._streak = [max(s, self.hysteresis_cycles - 1) for s in self._streak]

    def resolve(self, planned: str, available: Feasible) -> str:
        """The mode actually used at fusion time, given the data that is there now."""
        if planned in available:
            return planned
        if self.fusion_mode != "adaptive":
            return "vehicle-only"
        return next(m for m in MODES[MODES.index(planned):] if m in available)


_LEVELS = ("tracking", "planning", "vehicle-only")  # most to least accurate


def _level(mode: str) -> str:
    """The level a mode belongs to: "tracking" (intra, inter), "planning" or "vehicle-only"."""
    return "tracking" if mode in TRACKING_MODES else mode


def mode_reason(fusion_mode: str, mode: str, feasible: Feasible, withheld: set[str], *,
                intra_late: bool = False, not_synced: bool = False) -> str:
    """Why a cycle ran ``mode`` (one of ``MODE_REASONS``; the module doc defines them).

    ``feasible``: what the data allowed at fusion time; ``withheld``: the levels ("tracking",
    "planning") whose data some RSU's clock withheld (``ModeInputs.withheld``); ``intra_late``:
    the fixed intra mode waited for a slot's frame that did not come; ``not_synced``: an RSU's
    data is there without a clock estimate."""
    if fusion_mode == "adaptive":
        better = list(_LEVELS[:_LEVELS.index(_level(mode))])
    else:
        better = [] if mode == fusion_mode else [_level(fusion_mode)]
    if not better:
        return "best"
    if fusion_mode == "adaptive" and any(
            feasible.intra or feasible.inter if lv == "tracking" else feasible.planning for lv in better):
        return "hysteresis"
    if withheld.intersection(better):
        return "clock_uncertainty"
    if intra_late:
        return "intra_frame_late"
    return "not_synced" if not_synced else "no_rsu_data"
