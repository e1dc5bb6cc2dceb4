"""The base of every wire message and one object's model: ``ObjectState`` / ``FusedObject`` with
their quantised fields (``Position``, ``Yaw``, ... : value ranges of ``schemas.limits``, grids of
``schemas.quantize``).

Apart from ``schemas.messages`` (the lists and the other messages, built on these) so that
``schemas.columns``, which applies the very rules of these models to whole columns, can build
them without importing the messages that hold its columns.
"""

from __future__ import annotations

from typing import Annotated, ClassVar

from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from schemas import quantize as q
from schemas.classes import ObjectClass
from schemas.limits import (ACCEL_MAX_MPS2, AGE_MAX_S, HEIGHT_MAX_M, POSITION_MAX_M, SIZE_MAX_M, SOURCE_VEHICLE,
                            SPEED_MAX_MPS, UNKNOWN_VELOCITY_VAR, VARIANCE_MAX, YAW_RATE_MAX)


def _grid(step: float):
    return AfterValidator(lambda v: q.quantize(v, step))


def _yaw(v: float) -> float:
    # k in [-1800, 1799] so that the grid value stays inside [-pi, pi)
    k = q.code(q.wrap_angle(v), q.YAW_RAD)
    return (k - 3600 if k >= 1800 else k) * q.YAW_RAD


Position = Annotated[float, Field(ge=-POSITION_MAX_M, le=POSITION_MAX_M, allow_inf_nan=False), _grid(q.POSITION_M)]
Height = Annotated[float, Field(ge=-HEIGHT_MAX_M, le=HEIGHT_MAX_M, allow_inf_nan=False), _grid(q.POSITION_M)]
Size = Annotated[float, Field(ge=0.0, le=SIZE_MAX_M, allow_inf_nan=False), _grid(q.SIZE_M)]
Speed = Annotated[float, Field(ge=-SPEED_MAX_MPS, le=SPEED_MAX_MPS, allow_inf_nan=False), _grid(q.SPEED_MPS)]
Accel = Annotated[float, Field(ge=-ACCEL_MAX_MPS2, le=ACCEL_MAX_MPS2, allow_inf_nan=False), _grid(q.ACCEL_MPS2)]
Yaw = Annotated[float, Field(ge=-100.0, le=100.0, allow_inf_nan=False), AfterValidator(_yaw)]
YawRate = Annotated[
    float, Field(ge=-YAW_RATE_MAX, le=YAW_RATE_MAX, allow_inf_nan=False), _grid(q.YAW_RATE_RADPS)
]
Variance = Annotated[float, Field(ge=0.0, le=VARIANCE_MAX, allow_inf_nan=False), _grid(q.COV_M2)]
Covariance = Annotated[float, Field(ge=-VARIANCE_MAX, le=VARIANCE_MAX, allow_inf_nan=False), _grid(q.COV_M2)]
Confidence = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False), _grid(q.CONFIDENCE)]
AgeS = Annotated[float, Field(ge=0.0, le=AGE_MAX_S, allow_inf_nan=False), _grid(q.AGE_S)]


class Message(BaseModel):
    """Base of every wire message: immutable, no unknown keys, no NaN."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)
    TYPE: ClassVar[str] = "message"


class ObjectState(Message):
    """One object. Map frame on RSU lists, base_link on fused lists."""

    TYPE: ClassVar[str] = "object"
    id: Annotated[int, Field(ge=0, lt=2**32)]
    cls: ObjectClass = ObjectClass.UNKNOWN
    x: Position
    y: Position
    z: Height = 0.0
    length: Size
    width: Size
    height: Size = 1.5
    yaw: Yaw = 0.0
    vx: Speed = 0.0
    vy: Speed = 0.0
    ax: Accel = 0.0
    ay: Accel = 0.0
    yaw_rate: YawRate = 0.0
    cov_xx: Variance = 1.0
    cov_xy: Covariance = 0.0
    cov_yy: Variance = 1.0
    # velocity covariance (m^2/s^2); the default, the largest variance, means "not measured"
    cov_vxx: Variance = UNKNOWN_VELOCITY_VAR
    cov_vxy: Covariance = 0.0
    cov_vyy: Variance = UNKNOWN_VELOCITY_VAR
    confidence: Confidence = 1.0
    age_s: AgeS = 0.0


class FusedObject(ObjectState):
    """A fused object; ``sources`` is a bitmask of SOURCE_VEHICLE | SOURCE_RSU."""

    TYPE: ClassVar[str] = "fused_object"
    sources: Annotated[int, Field(ge=0, le=255)] = SOURCE_VEHICLE
