"""OBU pipeline (pure): clock sync, RSU buffering, delay compensation, fusion, deadlines.

Driven by calls, never by a clock or Zenoh: the live node and the offline runner feed
the same object. All times are OBU-clock nanoseconds unless named ``*_rsu_ns``.
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

from fusion.frames import Pose2D, map_to_base
from fusion.merger import iou_merge
from fusion.motion import predict_cv
from fusion.objects import ObjectArray
from fusion.pose_history import PoseHistory
from fusion.wire import objects_from_states, states_from_objects
from schemas.messages import SOURCE_RSU, SOURCE_VEHICLE, FusedObjectList, ObjectList, ObuMetrics, RsuLinkStatus, TimeReply, TimeRequest

from .clock_sync import ClockSync, SyncSample

FUSION_METHODS = ("iou-merge", "vehicle-only", "rsu-only")
RSU_ID_BASE = 1_000_000  # output ids of RSU objects: RSU_ID_BASE * (rsu index + 1) + RSU track id


@dataclass(frozen=True)
class ObuPipelineConfig:
    vehicle_id: str = "ego"
    fusion: str = "iou-merge"
    iou_threshold: float = 0.1  # seed 000 merger: an RSU object this overlapping an own one is a duplicate
    max_rsu_age_s: float = 1.0  # older RSU frames are not fused
    deadline_ms: float = 100.0  # end-to-end: own LiDAR capture -> publish
    sync_window: int = 16
    frames_kept: int = 8

    def __post_init__(self) -> None:
        if self.fusion not in FUSION_METHODS:
            raise ValueError(f"fusion must be one of {FUSION_METHODS}, got {self.fusion!r}")


@dataclass
class _RsuFrame:
    capture_rsu_ns: int
    receive_ns: int
    seq: int
    objects: ObjectArray  # map frame


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
        if not self._rsu(reply.rsu_id).sync.add(SyncSample(t1, reply.t2_ns, reply.t3_ns, t4_ns)):
            self.rejected["time_reply_inconsistent"] += 1

    def clock_offset(self, rsu_id: str):
        """Current offset estimate (theta = rsu - obu) of one RSU, or None."""
        state = self._rsus.get(rsu_id)
        return None if state is None else state.sync.estimate()

    # --- inputs ----------------------------------------------------------------------
    def on_pose(self, t_ns: int, pose: Pose2D) -> None:
        self.poses.add(t_ns, pose)

    def on_rsu_message(self, msg: ObjectList, receive_ns: int) -> None:
        state = self._rsu(msg.header.rsu_id)
        if any(f.seq == msg.header.seq for f in state.frames):
            self.rejected["duplicate"] += 1
            return
        frame = _RsuFrame(msg.header.capture_time_ns, receive_ns, msg.header.seq, objects_from_states(msg.objects))
        state.frames.append(frame)
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
        rsu = self._rsu_objects(cycle_ns, ego)
        fused = self._combine(own, rsu)
        self.last_mode = "inter" if len(rsu) and self.config.fusion != "vehicle-only" else "vehicle-only"
        self.cycles += 1
        late = now_ns > cycle_ns + int(self.config.deadline_ms * 1e6)
        self.deadline_misses += int(late)
        self._out_seq += 1
        return FusedObjectList(
            vehicle_id=self.config.vehicle_id, seq=self._out_seq, cycle_time_ns=cycle_ns, publish_time_ns=now_ns,
            fusion=self.config.fusion, mode=self.last_mode, ego_x=ego.x, ego_y=ego.y, ego_yaw=ego.yaw,
            objects=states_from_objects(fused, fused=True),
        )

    def _combine(self, own: ObjectArray, rsu: ObjectArray) -> ObjectArray:
        own = own.with_(ids=np.arange(1, len(own) + 1))
        if self.config.fusion == "vehicle-only":
            return own
        if self.config.fusion == "rsu-only":
            return rsu
        return iou_merge(own, rsu, self.config.iou_threshold)

    def _rsu_objects(self, cycle_ns: int, ego: Pose2D) -> ObjectArray:
        """Newest usable frame of each RSU, predicted to the cycle time, in base_link.

        Seed 000 eq. 3-4 move objects to base_link with the ego pose at capture time;
        here they are predicted in ``map`` first (p(t) = p + v (t - t_capture)) and then
        moved with the pose at the cycle time, which equals eq. 3-4 followed by ego-motion
        compensation from the capture to the cycle time.
        """
        parts = []
        for rsu_id, state in self._rsus.items():
            frame, capture_ns = self._newest_usable(state, cycle_ns)
            if frame is None:
                continue
            objs = predict_cv(frame.objects, (cycle_ns - capture_ns) * 1e-9)
            objs = map_to_base(objs, ego).with_(
                ids=RSU_ID_BASE * (state.index + 1) + frame.objects.ids, sources=np.full(len(objs), SOURCE_RSU)
            )
            parts.append(objs)
        return ObjectArray.concat(parts)

    def _newest_usable(self, state: _RsuState, cycle_ns: int) -> tuple[_RsuFrame | None, int]:
        est = state.sync.estimate()
        if est is None or not state.frames:
            return None, 0
        frame = max(state.frames, key=lambda f: f.capture_rsu_ns)
        capture_ns = frame.capture_rsu_ns - est.offset_ns  # t_obu = t_rsu - theta
        age_s = (cycle_ns - capture_ns) * 1e-9
        state.last_age_ms = age_s * 1e3
        return (frame, capture_ns) if abs(age_s) <= self.config.max_rsu_age_s else (None, 0)

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

    def _rsu(self, rsu_id: str) -> _RsuState:
        if rsu_id not in self._rsus:
            self._rsus[rsu_id] = _RsuState(index=len(self._rsus), sync=ClockSync(self.config.sync_window))
        return self._rsus[rsu_id]
