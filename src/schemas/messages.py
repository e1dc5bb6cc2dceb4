"""Wire message models. Frozen, strict (unknown keys rejected), quantised on construction.

All times are ``int`` nanoseconds since the Unix epoch in the clock of the node that
took them (``*_time_ns``). Positions are metres in the frame named by ``frame_id``.
"""

from __future__ import annotations

from typing import Annotated, ClassVar, Literal

from pydantic import Field, PlainSerializer, PlainValidator, ValidatorFunctionWrapHandler, WrapValidator, model_validator

from schemas.columns import ObjectColumns, objects_field
from schemas.limits import (ACCEL_MAX_MPS2, AGE_MAX_S, HEIGHT_MAX_M, MAX_OBJECTS, POSITION_MAX_M, SIZE_MAX_M,  # noqa: F401
                     SOURCE_RSU, SOURCE_VEHICLE, SPEED_MAX_MPS, UNKNOWN_VELOCITY_VAR, VARIANCE_MAX, YAW_RATE_MAX)
# the message base, one object's model and its fields (schemas.object_state), importable from here too
from schemas.object_state import (AgeS, Accel, Confidence, Covariance, FusedObject, Height, Message,  # noqa: F401
                                  ObjectState, Position, Size, Speed, Variance, Yaw, YawRate)
from schemas.path_points import grid_positions, grid_yaws, paths_from_array, paths_from_dicts, points_validator

# 2: velocity covariance cov_vxx, cov_vxy, cov_vyy on objects
# 3: header schema_version checked; RsuMetrics; ObuMetrics.output_dropped; RsuLinkStatus.sync_outliers
# 4: object lists as one msgpack array [v, tag, fields, objects]: positional fields (nil: default),
#    objects as bit-packed rows of per-message column widths (schemas.object_wire)
# 5: indexed object columns (a table of the column's distinct values, schemas.object_wire)
SCHEMA_VERSION = 5

# Plausible wall-clock range: 2000-01-01 .. 2100-01-01. Anything outside is a broken clock.
MIN_TIME_NS = 946_684_800 * 10**9
MAX_TIME_NS = 4_102_444_800 * 10**9

NodeId = Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]{1,64}$")]
TimeNs = Annotated[int, Field(ge=MIN_TIME_NS, le=MAX_TIME_NS)]
Seq = Annotated[int, Field(ge=0, lt=2**63)]
# Every integer must fit a msgpack int64 so that any valid message can be encoded.
Count = Annotated[int, Field(ge=0, lt=2**63)]
Int64 = Annotated[int, Field(ge=-(2**63), lt=2**63)]
# A message's own schema_version field must be this build's (a different one is read differently).
SchemaVersion = Annotated[int, Field(ge=SCHEMA_VERSION, le=SCHEMA_VERSION)]
# A list's objects: validated columns (schemas.columns), built from an ObjectColumns or from
# per-object models / dicts; ``FusedObjects`` carry ``sources``.
# (model_dump gives per-object dicts: for inspection, not for the wire.)
_AS_DICTS = PlainSerializer(lambda cols: [obj.model_dump() for obj in cols])
Objects = Annotated[ObjectColumns, PlainValidator(objects_field(fused=False)), _AS_DICTS]
FusedObjects = Annotated[ObjectColumns, PlainValidator(objects_field(fused=True)), _AS_DICTS]
EMPTY_OBJECTS = ObjectColumns.empty()
EMPTY_FUSED = ObjectColumns.empty(fused=True)


class ObjectListHeader(Message):
    TYPE: ClassVar[str] = "object_list_header"
    schema_version: SchemaVersion = SCHEMA_VERSION
    rsu_id: NodeId
    seq: Seq
    capture_time_ns: TimeNs
    publish_time_ns: TimeNs
    frame_id: Annotated[str, Field(max_length=64)] = "map"
    sensor: Annotated[str, Field(max_length=128)] = ""
    # The objects are valid at capture_time_ns + prediction_ns: non-zero when the RSU has
    # already predicted them forward (track-predict compensation, Saravanan et al. Algorithm 1).
    prediction_ns: Annotated[int, Field(ge=0, le=10_000_000_000)] = 0

    @property
    def valid_time_ns(self) -> int:
        return self.capture_time_ns + self.prediction_ns

    @model_validator(mode="after")
    def _publish_after_capture(self) -> "ObjectListHeader":
        if self.publish_time_ns < self.capture_time_ns:
            raise ValueError("publish_time_ns is before capture_time_ns (same RSU clock)")
        return self


class ObjectList(Message):
    """RSU -> vehicles on ``v2x/rsu/{rsu_id}/objects``; positions in ``map``."""

    TYPE: ClassVar[str] = "object_list"
    header: ObjectListHeader
    objects: Objects = EMPTY_OBJECTS


MAX_PATH_POINTS = 128  # 12.8 s at 0.1 s steps
_PATH_POSITIONS = points_validator(-POSITION_MAX_M, POSITION_MAX_M, MAX_PATH_POINTS, grid_positions)
_YAW_LIMIT = 100.0  # Yaw's range: [-100, 100]
_PATH_YAWS = points_validator(-_YAW_LIMIT, _YAW_LIMIT, MAX_PATH_POINTS, grid_yaws)


class PredictedPath(Message):
    """Predicted centre positions (map) of one object at t0 + k * step, k = 1..K."""

    TYPE: ClassVar[str] = "predicted_path"
    id: Annotated[int, Field(ge=0, lt=2**32)]
    # per-point rules of Position / Yaw, checked and gridded as arrays (schemas.path_points)
    x: Annotated[tuple[Position, ...], Field(max_length=MAX_PATH_POINTS), _PATH_POSITIONS] = ()
    y: Annotated[tuple[Position, ...], Field(max_length=MAX_PATH_POINTS), _PATH_POSITIONS] = ()
    yaw: Annotated[tuple[Yaw, ...], Field(max_length=MAX_PATH_POINTS), _PATH_YAWS] = ()

    @model_validator(mode="after")
    def _same_lengths(self) -> "PredictedPath":
        if not len(self.x) == len(self.y) == len(self.yaw):
            raise ValueError(f"x, y and yaw must have one entry per step, got {len(self.x)}, {len(self.y)}, {len(self.yaw)}")
        return self


_new_path = PredictedPath.__new__
_set_slot = object.__setattr__


def _path(path_id: int, x: tuple, y: tuple, yaw: tuple) -> PredictedPath:
    """A PredictedPath of values already checked and gridded (schemas.path_points): what
    ``PredictedPath.model_construct(id=path_id, x=x, y=y, yaw=yaw)`` builds (its fields and every
    field set; no extra, no private attributes, no post-init), without its generic per-field loop
    over aliases and defaults (test_path_points compares the two)."""
    path = _new_path(PredictedPath)
    _set_slot(path, "__dict__", {"id": path_id, "x": x, "y": y, "yaw": yaw})
    _set_slot(path, "__pydantic_fields_set__", {"id", "x", "y", "yaw"})
    _set_slot(path, "__pydantic_extra__", None)
    _set_slot(path, "__pydantic_private__", None)
    return path


def predicted_paths(ids, points) -> tuple[PredictedPath, ...]:
    """One PredictedPath per object: ids (N,), points (N, K, 3) [x, y, yaw] (map); checked and
    gridded as one array, or path by path by the model when something is out of range."""
    fast = paths_from_array(ids, points, MAX_PATH_POINTS, POSITION_MAX_M, _YAW_LIMIT)
    if fast is not None:
        return tuple(_path(*p) for p in fast)
    return tuple(PredictedPath(id=int(i), x=p[:, 0].tolist(), y=p[:, 1].tolist(), yaw=p[:, 2].tolist())
                 for i, p in zip(ids, points))


def _paths(value, handler: ValidatorFunctionWrapHandler) -> tuple[PredictedPath, ...]:
    """PredictionList.paths: decoded ``{id, x, y, yaw}`` dicts checked in one pass when plain
    and in range (schemas.path_points), anything else by the model (its errors)."""
    fast = paths_from_dicts(value, MAX_OBJECTS, MAX_PATH_POINTS, POSITION_MAX_M, _YAW_LIMIT)
    return handler(value) if fast is None else tuple(_path(*p) for p in fast)


class PredictionList(Message):
    """RSU -> vehicles on ``v2x/rsu/{rsu_id}/predictions``: long-horizon trajectories.

    ``objects`` are the tracks at ``header.valid_time_ns`` (t0, map frame) and
    ``paths[i]`` the predicted positions of ``objects[i]`` at t0 + k * step_ns, k = 1..K
    (IAAD's planning-fusion input).
    """

    TYPE: ClassVar[str] = "prediction_list"
    header: ObjectListHeader
    step_ns: Annotated[int, Field(ge=1_000_000, le=10_000_000_000)] = 100_000_000
    objects: Objects = EMPTY_OBJECTS
    paths: Annotated[tuple[PredictedPath, ...], Field(max_length=MAX_OBJECTS), WrapValidator(_paths)] = ()

    @model_validator(mode="after")
    def _one_path_per_object(self) -> "PredictionList":
        if len(self.paths) != len(self.objects):
            raise ValueError(f"{len(self.objects)} objects but {len(self.paths)} paths")
        for i, (obj_id, path) in enumerate(zip(self.objects.ids.tolist(), self.paths)):
            if obj_id != path.id:
                raise ValueError(f"paths.{i}.id {path.id} differs from objects.{i}.id {obj_id}")
        return self

    @property
    def horizon_ns(self) -> int:
        return self.step_ns * max((len(p.x) for p in self.paths), default=0)


class FusedObjectList(Message):
    """OBU output on ``v2x/obu/{vehicle_id}/objects``; positions in ``base_link``.

    ``cycle_time_ns`` is the own LiDAR capture time of the cycle (OBU clock); the
    ego pose (map frame) is the one used to express the objects in base_link.
    """

    TYPE: ClassVar[str] = "fused_object_list"
    schema_version: SchemaVersion = SCHEMA_VERSION
    vehicle_id: NodeId
    seq: Seq
    cycle_time_ns: TimeNs
    publish_time_ns: TimeNs
    frame_id: Annotated[str, Field(max_length=64)] = "base_link"
    fusion: Annotated[str, Field(max_length=32)] = ""
    mode: Annotated[str, Field(max_length=32)] = ""
    ego_x: Position = 0.0
    ego_y: Position = 0.0
    ego_yaw: Yaw = 0.0
    # why the cycle ran ``mode`` (obu_service.fusion_mode: best, hysteresis, clock_uncertainty, ...); ""
    # from producers that do not say. Last of the positional fields, so their shorter lists still decode
    mode_reason: Annotated[str, Field(max_length=32)] = ""
    objects: FusedObjects = EMPTY_FUSED


class TimeRequest(Message):
    """OBU -> RSU query payload on ``v2x/rsu/{rsu_id}/time``: t1 = OBU send time."""

    TYPE: ClassVar[str] = "time_request"
    obu_id: NodeId
    seq: Seq
    t1_ns: TimeNs


class TimeReply(Message):
    """RSU reply: t2 = RSU receive, t3 = RSU send (RSU clock); t1 echoed."""

    TYPE: ClassVar[str] = "time_reply"
    rsu_id: NodeId
    seq: Seq
    t1_ns: TimeNs
    t2_ns: TimeNs
    t3_ns: TimeNs

    @model_validator(mode="after")
    def _send_after_receive(self) -> "TimeReply":
        if self.t3_ns < self.t2_ns:
            raise ValueError("t3_ns (RSU send) is before t2_ns (RSU receive)")
        return self


class EgoPose(Message):
    """Vehicle pose in ``map`` on ``v2x/obu/{vehicle_id}/pose``."""

    TYPE: ClassVar[str] = "ego_pose"
    vehicle_id: NodeId
    t_ns: TimeNs
    x: Position
    y: Position
    yaw: Yaw = 0.0
    vx: Speed = 0.0
    vy: Speed = 0.0


class RsuLinkStatus(Message):
    """What the OBU knows about one RSU: clock relation and data flow."""

    TYPE: ClassVar[str] = "rsu_link_status"
    rsu_id: NodeId
    clock_offset_ns: Int64 | None = None  # theta = rsu_clock - obu_clock
    clock_uncertainty_ns: Int64 | None = None
    clock_drift_ppm: Annotated[float | None, Field(allow_inf_nan=False)] = None
    clock_offset_naive_ns: Int64 | None = None  # the latest single exchange, for comparison
    sync_samples: Count = 0
    sync_outliers: Count = 0  # time replies the clock filter rejected (forged, or outliers against its fit)
    clock_steps: Count = 0  # RSU clock steps the clock filter confirmed
    messages_accepted: Count = 0
    # lists the RSU numbered since the OBU first heard it (the span of their sequence numbers, per restart);
    # None: not counted (no list with a message counter yet)
    messages_sent: Count | None = None
    last_data_age_ms: Annotated[float | None, Field(allow_inf_nan=False)] = None
    delay_p50_ms: Annotated[float | None, Field(allow_inf_nan=False)] = None  # one-way, RSU publish -> OBU
    delay_p95_ms: Annotated[float | None, Field(allow_inf_nan=False)] = None
    jitter_ms: Annotated[float | None, Field(allow_inf_nan=False)] = None
    loss_ratio: Annotated[float | None, Field(ge=0.0, le=1.0, allow_inf_nan=False)] = None


StageName = Annotated[str, Field(pattern=r"^[a-z0-9_]{1,32}$")]
LatencyMsValue = Annotated[float, Field(ge=0.0, le=1e9, allow_inf_nan=False)]


class StageLatencyMs(Message):
    """One pipeline stage's durations (``v2i.telemetry.latency.StageLatency.summary_ms``): observations
    since start, and p50 <= p95 <= p99 in ms over the latest ones."""

    TYPE: ClassVar[str] = "stage_latency"
    count: Count
    p50: LatencyMsValue
    p95: LatencyMsValue
    p99: LatencyMsValue

    @model_validator(mode="after")
    def _ordered(self) -> "StageLatencyMs":
        if not self.p50 <= self.p95 <= self.p99:
            raise ValueError(f"quantiles out of order: p50 {self.p50}, p95 {self.p95}, p99 {self.p99}")
        return self


# per-stage latency of a service, by stage name (``latency_ms`` of the metrics); bounded like v2i.telemetry.latency
LatencyMs = Annotated[dict[StageName, StageLatencyMs], Field(max_length=32)]


class ObuMetrics(Message):
    """Periodic OBU health on ``v2x/obu/{vehicle_id}/metrics``."""

    TYPE: ClassVar[str] = "obu_metrics"
    vehicle_id: NodeId
    t_ns: TimeNs
    cycles: Count = 0
    output_deadline_misses: Count = 0  # published after capture + deadline, or after the interval bound
    rsu_deadline_misses: Count = 0  # covered cycles fused without RSU data (IAAD's metric)
    covered_cycles: Count = 0  # cycles with an RSU heard recently
    # cycles that fell back from their best mode within 1 s of the intake refusing a registered RSU's (or an own
    # sensor's) message: genuine input crowded out by a flood (obu_service.shell)
    crowded_out_cycles: Count = 0
    mode: Annotated[str, Field(max_length=32)] = ""
    mode_counts: dict[Annotated[str, Field(max_length=32)], Count] = Field(default_factory=dict, max_length=8)
    mode_reasons: dict[Annotated[str, Field(max_length=32)], Count] = Field(default_factory=dict, max_length=8)
    # the RSUs whose data the last cycle used (ObuPipeline.last_rsu_inputs); None: not stated (older producers)
    rsu_inputs: Annotated[tuple[NodeId, ...] | None, Field(max_length=64)] = None
    rsus: Annotated[tuple[RsuLinkStatus, ...], Field(max_length=64)] = ()
    rejected: dict[Annotated[str, Field(max_length=64)], Count] = Field(
        default_factory=dict, max_length=64
    )
    # output objects dropped (or clipped) to fit the wire, by reason
    output_dropped: dict[Annotated[str, Field(max_length=64)], Count] = Field(default_factory=dict, max_length=16)
    latency_ms: LatencyMs = Field(default_factory=dict)  # per stage (v2i.telemetry.latency): queue, decode, fuse, ...


Ratio = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)]
BinLabel = Annotated[str, Field(max_length=16)]
NonNegative = Annotated[float, Field(ge=0.0, le=1e9, allow_inf_nan=False)]


class RsuPerception(Message):
    """The RSU's raw detections scored against the simulated truth its camera could see
    (simulation only; ``v2i.perception.scoring``): the report's ``rsu_perception``."""

    frames: Count
    recall: Ratio | None = None
    precision: Ratio | None = None
    recall_by_range: dict[BinLabel, Ratio | None] = Field(default_factory=dict, max_length=8)
    visible_truths_by_range: dict[BinLabel, Count] = Field(default_factory=dict, max_length=8)
    mean_error_m: dict[BinLabel, NonNegative | None] = Field(default_factory=dict, max_length=8)
    detector_ms: dict[BinLabel, NonNegative] | None = Field(None, max_length=4)
    calibration_reprojection_px: NonNegative | None = None


class RsuMetrics(Message):
    """Periodic RSU health on ``v2x/rsu/{rsu_id}/metrics``."""

    TYPE: ClassVar[str] = "rsu_metrics"
    rsu_id: NodeId
    t_ns: TimeNs
    published: Count = 0  # object lists
    skipped: Count = 0  # frames not published because their time had passed (restart, stall)
    time_replies: Count = 0
    rejected: dict[Annotated[str, Field(max_length=64)], Count] = Field(default_factory=dict, max_length=64)
    perception: RsuPerception | None = None  # simulated sources: detections scored against the truth
    latency_ms: LatencyMs = Field(default_factory=dict)  # per stage (v2i.telemetry.latency): detect, encode, put, ...


class LinkControl(Message):
    """Runtime control of a link emulator on ``v2x/link/{link_id}/control`` (chaos tooling).

    Exactly one action: ``profile`` switches to a bundled profile (names only: a remote
    peer must not make the emulator read files), ``clear`` removes every impairment, or an
    impairment of ``duration_s`` from its receipt: ``outage``, ``extra_delay_ms``,
    ``loss_probability`` and/or ``bandwidth_kbps`` on ``direction``. ``vehicle_id`` limits it
    to that vehicle's channel of an emulator serving several (None: every channel).
    """

    TYPE: ClassVar[str] = "link_control"
    link_id: NodeId
    seq: Seq = 0
    vehicle_id: NodeId | None = None
    profile: Annotated[str | None, Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$")] = None
    clear: bool = False
    duration_s: Annotated[float | None, Field(gt=0.0, le=86_400.0, allow_inf_nan=False)] = None
    direction: Literal["uplink", "downlink", "both"] = "both"
    outage: bool = False
    extra_delay_ms: Annotated[float, Field(ge=0.0, le=600_000.0, allow_inf_nan=False)] = 0.0
    loss_probability: Annotated[float | None, Field(ge=0.0, le=1.0, allow_inf_nan=False)] = None
    bandwidth_kbps: Annotated[float | None, Field(gt=0.0, le=1e7, allow_inf_nan=False)] = None

    @property
    def impairs(self) -> bool:
        return self.outage or self.extra_delay_ms > 0 or self.loss_probability is not None or self.bandwidth_kbps is not None

    @model_validator(mode="after")
    def _one_action(self) -> "LinkControl":
        actions = [self.profile is not None, self.clear, self.impairs]
        if sum(actions) != 1:
            raise ValueError("exactly one action: profile, clear, or an impairment (outage / extra_delay_ms / "
                             "loss_probability / bandwidth_kbps)")
        if self.impairs and self.duration_s is None:
            raise ValueError("an impairment needs duration_s")
        return self
