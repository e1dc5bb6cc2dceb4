"""OBU pipeline (pure): clock sync, RSU buffering, delay compensation, fusion, deadlines.

Driven by calls, never by a clock or Zenoh: the live node and the offline runner feed
the same object. All times are OBU-clock nanoseconds unless named ``*_rsu_ns``.
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

from fusion.frames import Pose2D
from fusion.objects import ObjectArray
from fusion.pose_history import PoseHistory
from fusion.wire import objects_from_states, states_from_objects
from schemas.messages import SOURCE_RSU, SOURCE_VEHICLE, FusedObjectList, ObjectList, ObuMetrics, RsuLinkStatus, TimeReply, TimeRequest

from .clock_sync import ClockSync, SyncSample
from .methods import COMPENSATIONS, FUSION_METHODS, RsuFrame, make_fusion

__all__ = ["COMPENSATIONS", "FUSION_METHODS", "ObuPipeline", "ObuPipelineConfig"]

RSU_ID_BASE = 1_000_000  # output ids of RSU objects: RSU_ID_BASE * (rsu index + 1) + RSU track id
MAX_RSUS = 64  # distinct RSU ids tracked; more are rejected (a flood of ids must not grow memory)


@dataclass(frozen=True)
class ObuPipelineConfig:
    vehicle_id: str = "ego"
    fusion: str = "iou-merge"
    compensation: str = "predict"
    iou_threshold: float = 0.1  # seed 000 merger: an RSU object this overlapping an own one is a duplicate
    max_rsu_age_s: float = 1.0  # older RSU frames are not fused
    deadline_ms: float = 100.0  # end-to-end: own LiDAR capture -> publish
    sync_window: int = 16
    frames_kept: int = 8

    def __post_init__(self) -> None:
        make_fusion(self.fusion, self.compensation, self.iou_threshold)  # validates the pair


@dataclass
class _Received:
    """An RSU list as received: RSU-clock times, placed in OBU time at fusion time."""

    capture_rsu_ns: int
    valid_rsu_ns: int
    seq: int
    objects: ObjectArray  # map frame
    used: bool = False  # consumed by a tracking fusion (each list is a measurement once)


@dataclass
class _RsuState:
    index: int
    sync: ClockSync
    frames: deque = field(default_factory=deque)
    accepted: int = 0
    last_age_ms: float | None = None


class ObuPipeline:
    def __init__(self, config: ObuPipelineConfig = ObuPipelineConfig()):
        self.config = config
        self.poses = PoseHistory(horizon_s=10.0)
        self.rejected: Counter[str] = Counter()
        self.cycles = 0
        self.deadline_misses = 0
        self.last_mode = "vehicle-only"
        self._fusion = make_fusion(config.fusion, config.compensation, config.iou_threshold)
        self._rsus: dict[str, _RsuState] = {}
        self._own: tuple[int, ObjectArray] | None = None
        self._pending_sync: dict[int, int] = {}  # request seq -> t1_ns
        self._sync_seq = 0
        self._out_seq = 0

    # --- clock synchronisation -------------------------------------------------------
    def make_time_request(self, t1_ns: int) -> TimeRequest:
        """A request to send now (t1 = OBU send time); replies are matched by seq."""
        self._sync_seq += 1
        self._pending_sync[self._sync_seq] = t1_ns
        for seq in [s for s, t in self._pending_sync.items() if t1_ns - t > 10_000_000_000]:
            del self._pending_sync[seq]
        return TimeRequest(obu_id=self.config.vehicle_id, seq=self._sync_seq, t1_ns=t1_ns)

    def on_time_reply(self, reply: TimeReply, t4_ns: int) -> None:
        t1 = self._pending_sync.get(reply.seq)
        if t1 is None or t1 != reply.t1_ns:
            self.rejected["time_reply_unmatched"] += 1
            return
        state = self._rsu(reply.rsu_id)
        if state is not None and not state.sync.add(SyncSample(t1, reply.t2_ns, reply.t3_ns, t4_ns)):
            self.rejected["time_reply_inconsistent"] += 1

    def clock_offset(self, rsu_id: str):
        """Current offset estimate (theta = rsu - obu) of one RSU, or None."""
        state = self._rsus.get(rsu_id)
        return None if state is None else state.sync.estimate()

    # --- inputs ----------------------------------------------------------------------
    def on_pose(self, t_ns: int, pose: Pose2D) -> None:
        self.poses.add(t_ns, pose)

    def on_rsu_message(self, msg: ObjectList, receive_ns: int) -> None:  # noqa: ARG002 (kept for link stats)
        state = self._rsu(msg.header.rsu_id)
        if state is None:
            return
        if any(f.seq == msg.header.seq for f in state.frames):
            self.rejected["duplicate"] += 1
            return
        objects = objects_from_states(msg.objects)
        objects = objects.with_(ids=RSU_ID_BASE * (state.index + 1) + objects.ids, sources=np.full(len(objects), SOURCE_RSU))
        state.frames.append(_Received(msg.header.capture_time_ns, msg.header.valid_time_ns, msg.header.seq, objects))
        state.accepted += 1
        while len(state.frames) > self.config.frames_kept:
            state.frames.popleft()

    def on_detections(self, dets: ObjectArray, capture_ns: int) -> None:
        """Own LiDAR objects (base_link at capture_ns); each call starts a cycle."""
        self._own = (capture_ns, dets.with_(sources=np.full(len(dets), SOURCE_VEHICLE)))

    def reject(self, reason: str) -> None:
        """Count an input the shell could not decode (codec error reason)."""
        self.rejected[reason] += 1

    # --- the cycle -------------------------------------------------------------------
    def fuse(self, now_ns: int) -> FusedObjectList:
        """Fuse the current cycle's own objects with usable RSU data; publish time = now_ns."""
        if self._own is None:
            raise RuntimeError("fuse() before any on_detections()")
        cycle_ns, own = self._own
        ego = self.poses.at(cycle_ns) or Pose2D(0.0, 0.0, 0.0)
        newest, fresh = self._usable_frames(cycle_ns)
        fused = self._fusion.fuse(cycle_ns, ego, own.with_(ids=np.arange(1, len(own) + 1)), newest, fresh)
        self.last_mode = "inter" if (newest or fresh) and self.config.fusion != "vehicle-only" else "vehicle-only"
        self.cycles += 1
        self.deadline_misses += int(now_ns > cycle_ns + int(self.config.deadline_ms * 1e6))
        self._out_seq += 1
        return FusedObjectList(
            vehicle_id=self.config.vehicle_id, seq=self._out_seq, cycle_time_ns=cycle_ns, publish_time_ns=now_ns,
            fusion=self.config.fusion, mode=self.last_mode, ego_x=ego.x, ego_y=ego.y, ego_yaw=ego.yaw,
            objects=states_from_objects(fused, fused=True),
        )

    def _usable_frames(self, cycle_ns: int) -> tuple[list[RsuFrame], list[RsuFrame]]:
        """(newest usable frame of each RSU, frames not yet consumed by tracking), in OBU time.

        A frame is usable once the RSU clock is related to ours and while its age at the
        cycle, |cycle - valid|, is within max_rsu_age_s.
        """
        newest, fresh = [], []
        for state in self._rsus.values():
            est = state.sync.estimate()
            if est is None or not state.frames:
                continue
            frames = sorted(state.frames, key=lambda f: f.valid_rsu_ns)
            placed, previous = [], None
            for raw in frames:  # t_obu = t_rsu - theta
                previous = RsuFrame(state.index, raw.seq, raw.capture_rsu_ns - est.offset_ns,
                                    raw.valid_rsu_ns - est.offset_ns, raw.objects, previous)
                placed.append((raw, previous))
            age_s = (cycle_ns - placed[-1][1].valid_ns) * 1e-9
            state.last_age_ms = age_s * 1e3
            limit_ns = self.config.max_rsu_age_s * 1e9
            if abs(age_s) <= self.config.max_rsu_age_s:
                newest.append(placed[-1][1])
            for raw, frame in placed:
                if not raw.used and abs(cycle_ns - frame.valid_ns) <= limit_ns and frame.valid_ns <= cycle_ns:
                    raw.used = True
                    fresh.append(frame)
        return newest, fresh

    # --- reporting -------------------------------------------------------------------
    def metrics(self, now_ns: int) -> ObuMetrics:
        return ObuMetrics(
            vehicle_id=self.config.vehicle_id, t_ns=now_ns, cycles=self.cycles,
            output_deadline_misses=self.deadline_misses, mode=self.last_mode,
            rsus=tuple(self._rsu_status(rsu_id, s) for rsu_id, s in self._rsus.items()),
            rejected=dict(self.rejected),
        )

    def _rsu_status(self, rsu_id: str, state: _RsuState) -> RsuLinkStatus:
        est = state.sync.estimate()
        return RsuLinkStatus(
            rsu_id=rsu_id, clock_offset_ns=None if est is None else est.offset_ns,
            clock_uncertainty_ns=None if est is None else est.uncertainty_ns,
            sync_samples=0 if est is None else est.samples, messages_accepted=state.accepted,
            last_data_age_ms=state.last_age_ms,
        )

    def _rsu(self, rsu_id: str) -> _RsuState | None:
        if rsu_id not in self._rsus:
            if len(self._rsus) >= MAX_RSUS:
                self.rejected["too_many_rsus"] += 1
                return None
            self._rsus[rsu_id] = _RsuState(index=len(self._rsus), sync=ClockSync(self.config.sync_window))
        return self._rsus[rsu_id]
