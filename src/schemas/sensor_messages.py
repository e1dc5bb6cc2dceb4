"""Sensor input messages: what a node's own sensors (or an outside publisher) feed it.

These are the open inputs of the RSU and OBU services (``--source zenoh``) and what
``v2i world`` publishes; they never cross the link emulator (keys ``v2x/sensor/...`` and
``v2x/world/...``, ``schemas.keys``):

- ``SensorObjects`` on ``v2x/sensor/rsu/{rsu_id}/objects`` (an RSU camera's detections, frame
  ``map``) or ``v2x/sensor/vehicle/{vehicle_id}/objects`` (a vehicle LiDAR's detections, frame
  ``base_link`` at the capture time). The per-object fields, units and ranges are those of an
  RSU ``ObjectList`` (``messages.ObjectState``; ``id`` is the sensor's detection or track id).
- ``LocalizationPose`` on ``v2x/sensor/vehicle/{vehicle_id}/pose``: the vehicle's pose
  estimate in ``map`` with its error covariance. ``messages.EgoPose`` does not fit: the OBU
  propagates the pose error into the RSU objects' covariance (``v2i.core.frames``), so the input
  must state it.
- ``GroundTruth`` on ``v2x/world/truth``: the simulated world's actors and vehicles per time,
  for scoring and monitors; nothing in a service consumes it.

Times are ``int`` ns since the Unix epoch in the publisher's clock, which must be the clock of
the node that consumes the input (same host, or synchronised to it, e.g. by PTP).
"""

from __future__ import annotations

from typing import Annotated, ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from schemas.messages import (EMPTY_OBJECTS, SCHEMA_VERSION, VARIANCE_MAX, Message, NodeId, Objects, Position, SchemaVersion,
                       Seq, Size, Speed, TimeNs, Yaw)

SENSOR_FRAMES = ("map", "base_link")
MAX_PROCESSING_NS = 10_000_000_000  # ready_time_ns - capture_time_ns: a sensor that takes longer is broken
MAX_VEHICLES = 256
CORRELATION_TIME_MAX_S = 1e6
YAW_VARIANCE_MAX = 10.0  # rad^2: beyond (std > 3.2 rad) the heading is unknown anyway
_PSD_TOLERANCE = 1e-9
# Pose covariances are not quantised (float64 on the wire): a yaw variance of 2.5e-5 rad^2
# would vanish on the objects' 1e-4 grid.
PoseVariance = Annotated[float, Field(ge=0.0, le=VARIANCE_MAX, allow_inf_nan=False)]
PoseCovariance = Annotated[float, Field(ge=-VARIANCE_MAX, le=VARIANCE_MAX, allow_inf_nan=False)]


class SensorHeader(Message):
    """``sensor_id``: the RSU or vehicle the sensor belongs to (the id in its key); ``sensor``: a
    free description (``camera``, ``lidar/top``); ``frame_id``: ``map`` (RSU sensors, positions
    in the site frame) or ``base_link`` (vehicle sensors, positions relative to the vehicle at
    ``capture_time_ns``); ``ready_time_ns``: when the detections existed (capture + processing)."""

    TYPE: ClassVar[str] = "sensor_header"
    schema_version: SchemaVersion = SCHEMA_VERSION
    sensor_id: NodeId
    sensor: Annotated[str, Field(max_length=128)] = ""
    seq: Seq
    frame_id: Literal[SENSOR_FRAMES]
    capture_time_ns: TimeNs
    ready_time_ns: TimeNs

    @model_validator(mode="after")
    def _ready_after_capture(self) -> SensorHeader:
        processing_ns = self.ready_time_ns - self.capture_time_ns
        if processing_ns < 0:
            raise ValueError("ready_time_ns is before capture_time_ns (same sensor clock)")
        if processing_ns > MAX_PROCESSING_NS:
            raise ValueError(f"ready_time_ns is {processing_ns / 1e9:.3g} s after capture_time_ns, "
                             f"at most {MAX_PROCESSING_NS / 1e9:g} s")
        return self


class SensorObjects(Message):
    """One sensor frame's detections (``SensorHeader.frame_id`` frame), at most MAX_OBJECTS."""

    TYPE: ClassVar[str] = "sensor_objects"
    header: SensorHeader
    objects: Objects = EMPTY_OBJECTS


class LocalizationPose(Message):
    """A vehicle's pose estimate in ``map`` at ``t_ns``: position (m), heading (rad, CCW from +x),
    velocity over ground (m/s, map axes), and the covariance of the pose error over (x m, y m,
    yaw rad) as its six distinct entries (positive semi-definite). ``correlation_time_s``: how
    long the error persists (first-order Gauss-Markov; 0: independent between poses)."""

    TYPE: ClassVar[str] = "localization_pose"
    schema_version: SchemaVersion = SCHEMA_VERSION
    vehicle_id: NodeId
    seq: Seq = 0
    t_ns: TimeNs
    x: Position
    y: Position
    yaw: Yaw = 0.0
    vx: Speed = 0.0
    vy: Speed = 0.0
    cov_xx: PoseVariance = 0.0  # m^2
    cov_xy: PoseCovariance = 0.0  # m^2
    cov_yy: PoseVariance = 0.0  # m^2
    cov_xyaw: PoseCovariance = 0.0  # m rad
    cov_yyaw: PoseCovariance = 0.0  # m rad
    cov_yawyaw: Annotated[float, Field(ge=0.0, le=YAW_VARIANCE_MAX, allow_inf_nan=False)] = 0.0  # rad^2
    correlation_time_s: Annotated[float, Field(ge=0.0, le=CORRELATION_TIME_MAX_S, allow_inf_nan=False)] = 0.0

    @model_validator(mode="after")
    def _positive_semi_definite(self) -> LocalizationPose:
        cov = self.covariance()
        smallest = float(np.linalg.eigvalsh(cov)[0])
        if smallest < -_PSD_TOLERANCE * max(1.0, float(np.trace(cov))):
            raise ValueError(f"pose covariance is not positive semi-definite (smallest eigenvalue {smallest:.3g})")
        return self

    def covariance(self) -> np.ndarray:
        """(3, 3) covariance of the pose error over (x m, y m, yaw rad)."""
        return np.array([[self.cov_xx, self.cov_xy, self.cov_xyaw],
                         [self.cov_xy, self.cov_yy, self.cov_yyaw],
                         [self.cov_xyaw, self.cov_yyaw, self.cov_yawyaw]])


class VehicleTruth(Message):
    """The true pose (map; box centre) and box size of one connected vehicle."""

    TYPE: ClassVar[str] = "vehicle_truth"
    vehicle_id: NodeId
    x: Position
    y: Position
    yaw: Yaw = 0.0
    vx: Speed = 0.0
    vy: Speed = 0.0
    length: Size = 0.0
    width: Size = 0.0
    height: Size = 0.0


class GroundTruth(Message):
    """The simulated world at ``t_ns`` (its clock) in ``map``: every actor present (``objects``,
    ids = the world's actor ids, covariances zero) and every connected vehicle."""

    TYPE: ClassVar[str] = "ground_truth"
    schema_version: SchemaVersion = SCHEMA_VERSION
    seq: Seq
    t_ns: TimeNs
    scenario: Annotated[str, Field(max_length=128)] = ""
    frame_id: Literal["map"] = "map"
    objects: Objects = EMPTY_OBJECTS
    vehicles: Annotated[tuple[VehicleTruth, ...], Field(max_length=MAX_VEHICLES)] = ()
