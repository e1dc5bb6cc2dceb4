"""The vehicle's own sensing: what one frame of it is (``OwnFrame``), what the OBU needs of sensing
run inside it (``OwnSensing``: the simulator's LiDAR and localisation, ``v2i.sim.obu_sources``), and
received detection frames and poses (``--source zenoh``) and the cycle clock they drive."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from v2i.core.frames import Pose2D, PoseUncertainty
from v2i.core.objects import ObjectArray
from v2i.fusion.wire import objects_from_states
from schemas.messages import SOURCE_VEHICLE
from schemas.sensor_messages import LocalizationPose, SensorObjects


@dataclass(frozen=True)
class OwnFrame:
    capture_ns: int  # OBU clock (the true clock in simulation)
    pose: Pose2D  # localisation estimate, map frame
    detections: ObjectArray  # base_link


class OwnSensing(Protocol):
    """The vehicle's own sensing run inside the OBU (``--source sim``: ``v2i.sim.obu_sources``): its
    cycle times (its LiDAR's capture times) and, at each, the frame."""

    def cycle_times_ns(self, duration_s: float) -> np.ndarray: ...

    def capture(self, capture_ns: int) -> OwnFrame: ...


def pose_of(msg: LocalizationPose) -> Pose2D:
    """The pipeline's pose of a received localisation message, with its stated error statistics
    (none when the covariance is zero: an exact pose)."""
    cov = msg.covariance()
    uncertainty = PoseUncertainty(cov, msg.correlation_time_s) if cov.any() else None
    return Pose2D(msg.x, msg.y, msg.yaw, msg.vx, msg.vy, uncertainty)


def detections_of(msg: SensorObjects) -> ObjectArray:
    """A received detection frame as the LiDAR's detections are (base_link, ids -1)."""
    dets = objects_from_states(msg.objects)
    return dets.with_(ids=np.full(len(dets), -1, dtype=np.int64), sources=np.full(len(dets), SOURCE_VEHICLE))


class ExternalCycles:
    """The OBU's cycle clock when its detections come from outside (``--source zenoh``; pure).

    Each accepted detection frame starts a cycle at its capture time c. The next frame is
    expected at c + period; if none has started a cycle by (expected + ``wait_ns``, the cycle's
    fuse-by time), a gap cycle without own detections starts at the expected time, so the output
    stays on time whatever the inputs do (it fuses the RSU data it has; counted by the node).
    A frame captured less than half a period after the last cycle is late: its slot went out.
    Before any frame, the first slot is ``start_ns``.
    """

    def __init__(self, start_ns: int, period_ns: int, wait_ns: int):
        self.period_ns, self.wait_ns = period_ns, wait_ns
        self.last_cycle_ns: int | None = None
        self.next_capture_ns = start_ns

    def accept(self, capture_ns: int) -> bool:
        """Whether a frame captured at ``capture_ns`` starts a cycle (False: late, its slot went out)."""
        if self.last_cycle_ns is not None and capture_ns < self.last_cycle_ns + self.period_ns // 2:
            return False
        self._started(capture_ns)
        return True

    @property
    def gap_due_ns(self) -> int:
        """When a gap cycle starts if no frame comes first."""
        return self.next_capture_ns + self.wait_ns

    def gap(self, now_ns: int) -> int | None:
        """The capture time of the gap cycle to start now, or None when it is not due."""
        if now_ns < self.gap_due_ns:
            return None
        capture_ns = self.next_capture_ns
        self._started(capture_ns)
        return capture_ns

    def _started(self, capture_ns: int) -> None:
        self.last_cycle_ns, self.next_capture_ns = capture_ns, capture_ns + self.period_ns
