"""Fusion methods of the OBU (pure): how own objects and RSU frames become one list.

Every method sees, per cycle, the own LiDAR objects (base_link at the cycle time), the
newest usable frame of each RSU and the frames that arrived since the last cycle; it
returns the fused objects in base_link at the cycle time.

- ``vehicle-only``: own objects.
- ``rsu-only``: compensated RSU objects.
- ``iou-merge``: Saravanan et al.'s merger (RSU duplicates of own objects removed).
- ``nms``: non-maximum suppression over the pooled boxes.
- ``tclf``: DAIR-V2X time-compensated late fusion (two-frame RSU velocity).
- ``kf``: a Kalman-filter tracker in ``map`` updated with own LiDAR, then with each RSU
  frame once (Bidare's KF poster); with ``oosm`` compensation RSU frames are out-of-sequence
  measurements at their capture time and the filter is re-run from there. RSU objects
  are the RSU tracker's estimates (position and velocity with covariances), each RSU slot
  its own source bit (``v2i.fusion.tracking.slot_source``): a track only this RSU has seen
  takes the newest one as its state, since it already holds what the older ones said; a
  track another RSU also updates fuses it by covariance intersection (the two filters'
  errors are correlated); a track only the LiDAR also sees fuses its position in a Kalman
  update (``Tracker.update(..., estimates=True)``, rules in ``v2i.fusion.tracking``).
  ``kf-vehicle`` and ``kf-rsu`` are the same tracker fed by one source only (Bidare's poster's
  "LiDAR only KF" and "camera only KF" ablations).

Compensation of RSU objects (``--compensation``): ``none`` uses them where they were;
``predict`` extrapolates them to the cycle time at constant acceleration (OTVIC);
``track-predict`` uses the RSU's own prediction to its publish time (Saravanan et al.
Algorithm 1) and extrapolates only the delay measured on the vehicle; ``lane`` moves them
along their lanes of the scenario's Lanelet2 map (Frenet, constant speed; Saravanan et al.'s
lanelet-based predictor); ``oosm`` (kf only) feeds them to the filter at their own time.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from v2i.fusion.ego_map_tracker import EgoMapTracker
from v2i.core.frames import Pose2D, add_pose_uncertainty, base_to_map, map_to_base
from v2i.fusion.merger import iou_merge
from v2i.fusion.motion import predict_ca
from v2i.fusion.nms import nms_fuse
from v2i.core.objects import ObjectArray
from v2i.fusion.oosm import OosmTracker
from v2i.fusion.tclf import tclf_compensate, tclf_fuse
from v2i.fusion.tracking import TrackerConfig, slot_source

FUSION_METHODS = ("kf", "iou-merge", "nms", "tclf", "rsu-only", "vehicle-only", "kf-vehicle", "kf-rsu")
OWN_ONLY_METHODS = ("vehicle-only", "kf-vehicle")  # the vehicle's own data only: no RSU frames, paths or peers
COMPENSATIONS = ("predict", "none", "track-predict", "lane", "oosm")
Motion = Callable[[ObjectArray, float], ObjectArray]  # (objects, dt_s) -> objects dt_s later


@dataclass(frozen=True)
class RsuFrame:
    """One RSU object list placed in OBU time. Times are OBU-clock ns."""

    rsu_index: int
    seq: int
    capture_ns: int
    valid_ns: int  # capture + the RSU's own prediction horizon
    objects: ObjectArray  # map frame, sources = slot_source(rsu_index)
    previous: "RsuFrame | None" = None  # the frame before, for two-frame velocity (TCLF)


def compensate(frame: RsuFrame, t_ns: int, mode: str, motion: Motion = predict_ca) -> ObjectArray:
    """RSU objects (map) moved to ``t_ns`` by ``motion`` (none: left where they were)."""
    if mode == "none":
        return frame.objects
    return motion(frame.objects, (t_ns - frame.valid_ns) * 1e-9)


class StatelessFusion:
    """The late-fusion baselines: each cycle from scratch with the newest RSU frames."""

    def __init__(self, method: str, compensation: str, iou_threshold: float, motion: Motion = predict_ca):
        self.method, self.compensation, self.iou_threshold, self.motion = method, compensation, iou_threshold, motion

    def used(self, newest: list[RsuFrame], fresh: list[RsuFrame]) -> list[RsuFrame]:
        """The frames ``fuse`` puts into its output: the newest of each RSU (none for vehicle-only)."""
        return [] if self.method == "vehicle-only" else newest

    def fuse(self, cycle_ns: int, ego: Pose2D, own: ObjectArray, newest: list[RsuFrame], fresh: list[RsuFrame]) -> ObjectArray:
        if self.method == "vehicle-only":
            return own
        rsu = ObjectArray.concat([map_to_base(self._rsu_at(f, cycle_ns), ego) for f in newest])
        if self.method == "rsu-only":
            return rsu
        if self.method == "iou-merge":
            return iou_merge(own, rsu, self.iou_threshold)
        if self.method == "nms":
            return nms_fuse(own, rsu, self.iou_threshold)
        return tclf_fuse(own, rsu)

    def _rsu_at(self, frame: RsuFrame, cycle_ns: int) -> ObjectArray:
        if self.method != "tclf":
            return compensate(frame, cycle_ns, self.compensation, self.motion)
        prev = frame.previous
        frame_dt_s = (frame.valid_ns - prev.valid_ns) * 1e-9 if prev else 0.0
        return tclf_compensate(prev.objects if prev else None, frame.objects, frame_dt_s,
                               (cycle_ns - frame.valid_ns) * 1e-9)


class KalmanFusion:
    """Tracking fusion in ``map``: predict, update with own LiDAR, then with each fresh RSU frame.

    The gate is ``either`` (distance or Mahalanobis): an RSU sees a far target first with an
    uncertain velocity, and at its next list (0.4 s later over a lossy link) the young track can
    be 6 m off; the distance gate alone spawned a second track there (red-light-runner seed 0,
    one identity switch at first acquisition)."""

    def __init__(self, compensation: str, use_own: bool = True, use_rsu: bool = True,
                 tracker: TrackerConfig = TrackerConfig(accel_std_mps2=1.0, gate="either"),
                 motion: Motion = predict_ca):
        self.compensation, self.use_own, self.use_rsu, self.motion = compensation, use_own, use_rsu, motion
        self._ego_map = EgoMapTracker(tracker)  # a Tracker in the map of the drifting pose estimate
        self.tracker = OosmTracker(self._ego_map) if compensation == "oosm" else self._ego_map
        self._ref_ns: int | None = None

    def used(self, newest: list[RsuFrame], fresh: list[RsuFrame]) -> list[RsuFrame]:
        """The frames ``fuse`` feeds to the tracker: the fresh ones (none for kf-vehicle)."""
        return fresh if self.use_rsu else []

    def fuse(self, cycle_ns: int, ego: Pose2D, own: ObjectArray, newest: list[RsuFrame], fresh: list[RsuFrame]) -> ObjectArray:
        if self._ref_ns is None:
            self._ref_ns = cycle_ns
        t_s = self._t(cycle_ns)
        # the tracker lives in map as the estimated pose places it (v2i.core.frames): own objects
        # enter it and tracks leave it without the pose covariance, RSU objects (true map) with it
        self._ego_map.ego = ego
        if self.use_own:
            self._update(base_to_map(own, ego, pose_uncertainty=False), t_s, own.sources)
        for frame in sorted(fresh, key=lambda f: f.valid_ns) if self.use_rsu else ():
            # oosm: a measurement at its own time, re-filtered into the past; else moved to the cycle
            at_ns = frame.valid_ns if self.compensation == "oosm" else cycle_ns
            rsu = add_pose_uncertainty(self._as_measurement(frame, at_ns), ego)
            self._update(rsu, self._t(at_ns), slot_source(frame.rsu_index), estimates=True)
        return map_to_base(self._tracks(t_s), ego, pose_uncertainty=False)

    def _as_measurement(self, frame: RsuFrame, cycle_ns: int) -> ObjectArray:
        # R = C + dt^2 C_v: moving the estimate by v dt adds the velocity's uncertainty
        dt_s = (cycle_ns - frame.valid_ns) * 1e-9 if self.compensation != "none" else 0.0
        objs = compensate(frame, cycle_ns, self.compensation, self.motion)
        return objs.with_(cov_xy=objs.cov_xy + dt_s**2 * objs.cov_vxy)

    def _update(self, dets: ObjectArray, t_s: float, sources, estimates: bool = False) -> None:
        """One batch into the tracker; ``sources``: the batch's bitmask, or its objects' (K,) masks."""
        mask = sources if isinstance(sources, int) else int(np.bitwise_or.reduce(np.atleast_1d(sources)))
        self.tracker.update(dets, t_s, mask, estimates)  # Tracker.update predicts to t_s first

    def _tracks(self, t_s: float) -> ObjectArray:
        if isinstance(self.tracker, OosmTracker):
            return self.tracker.tracks(t_s)
        self.tracker.prune(t_s)
        return self.tracker.tracks(t_s)

    def _t(self, t_ns: int) -> float:
        return (t_ns - self._ref_ns) * 1e-9


def check_fusion(method: str, compensation: str) -> None:
    """ValueError unless ``method`` and ``compensation`` are known and go together."""
    if method not in FUSION_METHODS:
        raise ValueError(f"fusion must be one of {FUSION_METHODS}, got {method!r}")
    if compensation not in COMPENSATIONS:
        raise ValueError(f"compensation must be one of {COMPENSATIONS}, got {compensation!r}")
    if compensation == "oosm" and not method.startswith("kf"):
        raise ValueError("compensation 'oosm' needs a filter to re-run: use it with --fusion kf")


def make_fusion(method: str, compensation: str, iou_threshold: float = 0.1, lanes=None):
    """The fusion object for a method and compensation (validated); ``lanes`` (a
    ``v2i.fusion.lane_prediction.LanePredictor``) is needed by the ``lane`` compensation."""
    check_fusion(method, compensation)
    motion = predict_ca
    if compensation == "lane":
        if lanes is None:
            raise ValueError("compensation 'lane' needs the scenario's Lanelet2 map")
        motion = lanes.predict_objects
    if method.startswith("kf"):
        return KalmanFusion(compensation, use_own=method != "kf-rsu", use_rsu=method != "kf-vehicle", motion=motion)
    return StatelessFusion(method, compensation, iou_threshold, motion)
