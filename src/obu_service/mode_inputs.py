"""The RSU data each fusion mode can use at a cycle (pure). Times are OBU-clock ns.

An RSU's lists are kept as received (``Received``: RSU-clock stamps) and placed in OBU time
with the RSU's current clock estimate each time they are looked at (``placed``), so a better
estimate re-places them; a list valid later than its own arrival (beyond the clock uncertainty
and the future tolerance) is left out. ``inter``: the newest frame of each RSU and the frames
not yet fed to the tracker within ``inter_max_age_s``; ``intra_slots`` / ``intra``: the frame
of each RSU's sensing slot; ``planning``: the newest paths that still cover the cycle;
``consume`` marks frames fed to the tracker (each list is a measurement once).

Clock gating: an RSU's data is only as well placed in time as its clock estimate. An RSU
whose stated uncertainty at the cycle (``OffsetEstimate.uncertainty_ns``, a bound on
|estimate - truth|) exceeds ``max_clock_uncertainty_ms`` offers no frames to intra or inter,
and one past ``planning_max_clock_uncertainty_ms`` no paths to planning (the bounds and their
derivation: ``ObuPipelineConfig``); another RSU with a good clock still offers its own.
``withheld`` says which modes' data some RSU's clock withheld at a cycle (the cycle's
``mode_reason``, ``obu_service.fusion_mode``).

Clock steps: a list stamped before a confirmed RSU clock step keeps the old clock's estimate
(``Received.clock``, named by ``RsuState.clock_of``) and is placed by it, the others by the
current one; the frames are ordered by their placed valid times (the RSU's stamps jump at a
step), so the tracker keeps its tracks across the step.
"""

from __future__ import annotations

import itertools
import statistics
from dataclasses import dataclass
from functools import cached_property
from operator import is_, itemgetter

from v2i.core.objects import ObjectArray
from schemas.messages import PredictionList

from obu_service.methods import RsuFrame
from obu_service.rsu_table import RsuState, RsuTable

DEFAULT_RSU_PERIOD_NS = 200_000_000  # until two RSU captures have been seen (5 Hz camera)
MIN_SLOT_TOLERANCE_NS = 1_000_000  # intra: captures this close to the cycle's count as its slot, at least


@dataclass
class Received:
    """An RSU list as received: RSU-clock times, placed in OBU time at fusion time."""

    capture_rsu_ns: int
    valid_rsu_ns: int
    seq: int
    objects: ObjectArray  # map frame
    receive_ns: int
    used: bool = False  # consumed by a tracking fusion (each list is a measurement once)
    # the estimate that places it instead of the RSU's current one: the old clock's for a list stamped
    # before a confirmed clock step (RsuState.clock_of); None: the current estimate
    clock: object = None


@dataclass(frozen=True)
class Placement:
    """``ModeInputs.placed``'s answer for one RSU (kept in ``RsuState.placement``), valid while
    the RSU's estimate and its frames are these."""

    estimate: object  # OffsetEstimate (frozen: compared by value)
    frames: tuple[Received, ...]  # compared by identity
    placed: tuple[tuple[Received, RsuFrame], ...]

    def holds(self, est, frames) -> bool:
        return ((self.estimate is est or self.estimate == est) and len(self.frames) == len(frames)
                and all(map(is_, self.frames, frames)))  # (each frame the very same object)

    @cached_property
    def period_ns(self) -> int:
        """``rsu_period_ns`` of these frames (asked each cycle by intra_slots and intra), from their
        placed captures: across a clock step the RSU's own stamps jump."""
        return _median_period_ns(f.capture_ns for _, f in self.placed)


class ModeInputs:
    """Which RSU data each mode can use; ``config`` is the OBU pipeline's configuration."""

    def __init__(self, config, rsus: RsuTable):
        self.config, self.rsus = config, rsus

    def placed(self, state: RsuState, t_ns: int) -> list[tuple[Received, RsuFrame]]:
        """The RSU's frames in OBU time (by valid time), each linked to the one before; [] before
        sync. A frame valid later than its own arrival (beyond the clock uncertainty and the
        future tolerance) is left out: it was admitted before the clock was known. The answer
        is reused while the RSU's estimate at t_ns and its frames are unchanged."""
        placement = self._placement(state, t_ns)
        return [] if placement is None else list(placement.placed)

    def _placement(self, state: RsuState, t_ns: int) -> Placement | None:
        """``placed``'s answer as kept in ``state.placement`` (None before sync)."""
        est = state.sync.estimate_at(t_ns)
        if est is None:
            return None
        last = state.placement  # a cycle asks about 6 times (intra_slots, intra, inter, consume)
        if last is not None and last.holds(est, state.frames):
            return last
        state.placement = Placement(est, tuple(state.frames), tuple(self._place(state, est)))
        return state.placement

    def _place(self, state: RsuState, est) -> list[tuple[Received, RsuFrame]]:
        tolerance_ns = est.uncertainty_ns + self.config.future_tolerance_ms * 1e6
        times = []
        # t_obu = t_rsu - theta(t): est.to_obu_ns, t = t0 + (r - t0 - theta0) / (1 + d), inlined (the
        # same operations) for the tens of frames placed per RSU and cycle; a frame stamped before a
        # clock step by its old clock's estimate (raw.clock)
        at_ns, theta0_ns, scale = est.at_ns, est.offset_ns, 1.0 + est.drift_ppm * 1e-6
        for raw in state.frames:
            if raw.clock is None:
                valid_ns = at_ns + round((raw.valid_rsu_ns - at_ns - theta0_ns) / scale)
                capture_ns = at_ns + round((raw.capture_rsu_ns - at_ns - theta0_ns) / scale)
            else:
                valid_ns, capture_ns = raw.clock.to_obu_ns(raw.valid_rsu_ns), raw.clock.to_obu_ns(raw.capture_rsu_ns)
            if valid_ns - raw.receive_ns <= tolerance_ns:
                times.append((valid_ns, capture_ns, raw))
        placed, previous = [], None
        for valid_ns, capture_ns, raw in sorted(times, key=_first):  # by valid time (OBU: stamps jump at a step)
            previous = RsuFrame(state.index, raw.seq, capture_ns, valid_ns, raw.objects, previous)
            placed.append((raw, previous))
        return placed

    def clock_ok(self, state: RsuState, t_ns: int, planning: bool = False) -> bool:
        """Whether the RSU's clock is known well enough at ``t_ns`` for the tracking modes (intra, inter)
        or, with ``planning``, for planning paths: stated uncertainty <= the mode's bound."""
        est = state.sync.estimate_at(t_ns)
        if est is None:
            return False
        bound_ms = self.config.planning_max_clock_uncertainty_ms if planning else self.config.max_clock_uncertainty_ms
        return est.uncertainty_ns <= bound_ms * 1e6

    def inter(self, t_c: int) -> tuple[list[RsuFrame], list[RsuFrame]]:
        """(newest frame of each RSU, frames not yet consumed) within inter_max_age_s of the cycle,
        of the RSUs whose clock passes the tracking bound (``clock_ok``)."""
        newest, fresh = [], []
        for state in self.rsus:
            got_newest, got_fresh = self._inter_of(state, t_c)
            if (got_newest or got_fresh) and self.clock_ok(state, t_c):
                newest += got_newest
                fresh += got_fresh
        return newest, fresh

    def _inter_of(self, state: RsuState, t_c: int) -> tuple[list[RsuFrame], list[RsuFrame]]:
        """One RSU's part of ``inter``, whatever its clock (and its ``last_age_ms`` at the cycle)."""
        placed = self.placed(state, t_c)
        if not placed:
            return [], []
        limit_ns = self.config.inter_max_age_s * 1e9
        state.last_age_ms = (t_c - placed[-1][1].valid_ns) * 1e-6
        newest = [placed[-1][1]] if abs(t_c - placed[-1][1].valid_ns) <= limit_ns else []
        fresh = [f for raw, f in placed if not raw.used and f.valid_ns <= t_c and t_c - f.valid_ns <= limit_ns]
        return newest, fresh

    def withheld(self, t_c: int) -> set[str]:
        """The levels ("tracking": intra / inter, "planning") for which some RSU had data at the cycle
        that its clock's uncertainty withheld (past the level's bound)."""
        out = set()
        for state in self.rsus:
            if not self.clock_ok(state, t_c) and any(self._inter_of(state, t_c)):
                out.add("tracking")
            if not self.clock_ok(state, t_c, planning=True) and self._paths_of(state, t_c) is not None:
                out.add("planning")
        return out

    def intra(self, capture_ns: int, slots: dict[str, int]) -> tuple[list[RsuFrame], list[RsuFrame]]:
        """(frames of the cycle's sensing slot, those of them not yet fed to the tracker), once
        every awaited one has arrived; ([], []) before."""
        frames, fresh = [], []
        for rsu_id, slot_ns in slots.items():
            state = self.rsus.get(rsu_id)
            if state is None or not self.clock_ok(state, capture_ns):  # expired, or its clock got uncertain, meanwhile
                return [], []
            placement = self._placement(state, capture_ns)
            match = [] if placement is None else [(raw, f) for raw, f in placement.placed
                                                  if abs(f.capture_ns - slot_ns) < placement.period_ns / 2]
            if not match:
                return [], []
            raw, frame = max(match, key=lambda m: m[1].valid_ns)
            frames.append(frame)
            fresh += [] if raw.used else [frame]
        return frames, fresh

    def intra_slots(self, t_c: int, fuse_by_ns: int) -> dict[str, int]:
        """RSU id -> capture (OBU ns) of its frame for this cycle's slot, for the RSUs whose
        frame is already here or will be by fuse_by with probability >= intra_min_probability
        (every RSU heard from, in the fixed ``intra`` mode).

        The slot's frame is the newest RSU capture at or before t_c + u, u the stated clock
        uncertainty (at least MIN_SLOT_TOLERANCE_NS, at most half a period): a capture at the
        cycle's own instant belongs to its slot whatever the sign of the clock error. When it has
        not arrived yet its capture is predicted from the last one: c* = c_last + n T,
        n = floor((t_c + u - c_last) / T), T the RSU's frame period.
        """
        slots = {}
        for state in self.rsus:
            placement = self._placement(state, t_c)
            if placement is None or not self.clock_ok(state, t_c):
                continue
            est, period_ns = placement.estimate, placement.period_ns
            reach_ns = t_c + min(max(est.uncertainty_ns, MIN_SLOT_TOLERANCE_NS), period_ns // 2)
            captures = [f.capture_ns for _, f in placement.placed if f.capture_ns <= reach_ns]
            if not captures:
                continue
            last_ns = max(captures)
            slot_ns = last_ns + ((reach_ns - last_ns) // period_ns) * period_ns
            if slot_ns - last_ns > period_ns and self.config.fusion_mode != "intra":
                continue  # frames are already missing: the link is not delivering, do not wait on it
            p_on_time = 1.0 if slot_ns == last_ns else state.monitor.arrival_probability((fuse_by_ns - slot_ns) * 1e-6)
            if p_on_time >= self.config.intra_min_probability or self.config.fusion_mode == "intra":
                slots[state.rsu_id] = slot_ns
        return slots

    def consume(self, fused: list[RsuFrame], t_c: int) -> None:
        """Mark frames fed to the tracker as used (each is a measurement once). In the fixed
        intra mode every frame of this slot or before is used up: intra never fuses late data."""
        done = {(f.rsu_index, f.seq) for f in fused}
        for state in self.rsus:
            for raw, frame in self.placed(state, t_c):
                late = self.config.fusion_mode == "intra" and frame.capture_ns <= t_c
                raw.used = raw.used or late or (state.index, raw.seq) in done

    def planning(self, t_c: int) -> list[tuple[PredictionList, int]]:
        """(paths, t0 in OBU ns) of each RSU whose newest paths still cover the cycle and whose clock
        passes the planning bound (``clock_ok``)."""
        out = []
        for state in self.rsus:
            item = self._paths_of(state, t_c)
            if item is not None and self.clock_ok(state, t_c, planning=True):
                out.append(item)
        return out

    def _paths_of(self, state: RsuState, t_c: int) -> tuple[PredictionList, int] | None:
        """The RSU's newest paths and their t0 (OBU ns) if they cover the cycle, whatever its clock."""
        pred, est = state.predictions, state.sync.estimate_at(t_c)
        if pred is None or est is None:
            return None
        t0_ns = (state.predictions_clock or est).to_obu_ns(pred.header.valid_time_ns)
        if 0 <= t_c - t0_ns <= min(self.config.planning_max_age_s * 1e9, pred.horizon_ns):
            return pred, t0_ns
        return None


_first = itemgetter(0)


def rsu_period_ns(state: RsuState) -> int:
    """Median interval between the RSU's distinct captures (RSU clock; drift is negligible
    here), at least 1 ms. (At most ``frames_kept`` captures: plain Python beats numpy here.)"""
    return _median_period_ns(f.capture_rsu_ns for f in state.frames)


def _median_period_ns(capture_times_ns) -> int:
    captures = sorted(set(capture_times_ns))
    if len(captures) < 2:
        return DEFAULT_RSU_PERIOD_NS
    return max(int(statistics.median(b - a for a, b in itertools.pairwise(captures))), 1_000_000)

