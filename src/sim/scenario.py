"""Scenarios as data: frozen pydantic models of a YAML scenario file.

A scenario is a ground-truth world (ego, actors, static buildings) plus the sensor models
that observe it (roadside camera, on-board LiDAR, localisation). Frame ``map``: x east,
y north, metres; angles in the YAML are degrees where named ``*_deg``, radians otherwise.

Trajectory model: a polyline ``path`` in map (m) and a piecewise-linear speed profile
``speed: [[t_s, mps], ...]`` (constant before the first and after the last key); see
``sim.world`` for the kinematics.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from shapely.geometry import Polygon
from shapely.validation import explain_validity

from schemas.classes import ObjectClass
from schemas.config import ConfigError, bundled_names, load_bundled_or_file

Point2 = tuple[float, float]
PosFloat = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
NonNeg = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
Probability = Annotated[float, Field(ge=0.0, le=1.0)]


class ScenarioError(ConfigError):
    """A scenario that cannot be loaded; the message names the file and the bad field."""


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", populate_by_name=True)


class Trajectory(_Frozen):
    """Polyline path (map, m) + speed profile [[t_s, mps], ...]; single point = static."""

    path: list[tuple[Finite, Finite]] = Field(min_length=1)
    speed: list[tuple[Finite, NonNeg]] = Field(default_factory=lambda: [(0.0, 0.0)], min_length=1)
    yaw_deg: Finite | None = None  # heading of a static (single-point) actor

    @field_validator("path")
    @classmethod
    def _distinct_points(cls, path: list[Point2]) -> list[Point2]:
        for i in range(1, len(path)):
            if path[i] == path[i - 1]:
                raise ValueError(f"path points {i - 1} and {i} coincide (zero-length segment)")
        return path

    @field_validator("speed")
    @classmethod
    def _increasing_times(cls, speed: list[Point2]) -> list[Point2]:
        times = [t for t, _ in speed]
        if any(b <= a for a, b in zip(times, times[1:])):
            raise ValueError(f"speed key times must strictly increase, got {times}")
        return speed

    @model_validator(mode="after")
    def _yaw_only_when_static(self) -> "Trajectory":
        if self.yaw_deg is not None and len(self.path) > 1:
            raise ValueError("yaw_deg is only for a single-point (static) path; a path's heading is its tangent")
        return self

    @property
    def is_static(self) -> bool:
        return len(self.path) == 1


class Body(_Frozen):
    """The ego or an actor: a named box of a class following a trajectory."""

    name: str = Field(min_length=1)
    cls: ObjectClass = Field(alias="class")
    size: tuple[PosFloat, PosFloat, PosFloat]  # length, width, height (m)
    trajectory: Trajectory

    @field_validator("cls", mode="before")
    @classmethod
    def _parse_class(cls, value: Any) -> ObjectClass:
        return ObjectClass.parse(value)


class BoxGeometry(_Frozen):
    """Rotated rectangle: centre (m), length along yaw, width across (m), yaw (deg)."""

    x: Finite
    y: Finite
    l: PosFloat  # noqa: E741 (the field's name in every AV dataset)
    w: PosFloat
    yaw_deg: Finite = 0.0


class Building(_Frozen):
    """Static occluder: blocks line of sight, is never an object. Exactly one of box/polygon."""

    name: str = ""
    box: BoxGeometry | None = None
    polygon: list[tuple[Finite, Finite]] | None = Field(default=None, min_length=3)

    @model_validator(mode="after")
    def _exactly_one_shape(self) -> "Building":
        if (self.box is None) == (self.polygon is None):
            raise ValueError("give exactly one of 'box' or 'polygon'")
        if self.polygon is not None and not Polygon(self.polygon).is_valid:
            raise ValueError(f"polygon must be simple (no self-intersection): {explain_validity(Polygon(self.polygon))}")
        return self


class Position3(_Frozen):
    x: Finite
    y: Finite
    z: Finite = 0.0


class ErrorBand(_Frozen):
    """Mean Euclidean position error (m) for objects up to ``max_range_m`` from the camera."""

    max_range_m: PosFloat
    mean_error_m: NonNeg


def _carom_bands() -> list[ErrorBand]:
    # CAROM (seed 000 Sec. I): ~0.8 m within 50 m of the camera, ~1.7 m from 50 to 120 m
    return [ErrorBand(max_range_m=50.0, mean_error_m=0.8), ErrorBand(max_range_m=120.0, mean_error_m=1.7)]


class ImageConfig(_Frozen):
    """The physical camera behind an image source: what ``sim.camera`` renders and the
    detector sees. Unset angles come from the sensor they belong to; ``pitch_deg`` None on an
    RSU aims the optical axis at the ground 0.45 range_m out. ``distortion``: OpenCV k1, k2."""

    yaw_deg: Finite | None = None
    pitch_deg: Annotated[float, Field(ge=-89.0, le=89.0)] | None = None
    fov_deg: Annotated[float, Field(gt=1.0, le=120.0)] | None = None  # horizontal; a pinhole beyond 120 deg is useless
    width: Annotated[int, Field(ge=64, le=4096)] = 640
    height: Annotated[int, Field(ge=64, le=4096)] = 384
    distortion: tuple[Finite, Finite] = (0.0, 0.0)
    # Wind sway of the mount: the standard deviation of each of yaw, pitch and roll (deg) about
    # the nominal pose, oscillating near the mount's first natural frequency ``sway_hz``
    # (``sim.camera.Sway``). None: the mount's default (an RSU pole RSU_SWAY_DEG, a vehicle 0).
    sway_deg: Annotated[float, Field(ge=0.0, le=5.0)] | None = None
    sway_hz: Annotated[float, Field(gt=0.0, le=50.0)] = 1.0


class RsuCameraConfig(_Frozen):
    """Roadside monocular camera (CAROM-like detector) on a pole."""

    id: str = Field(pattern=r"^[A-Za-z0-9_-]{1,64}$")
    position: Position3  # camera on the pole, map frame (m)
    yaw_deg: Finite  # optical axis heading, CCW from +x (deg)
    fov_deg: Annotated[float, Field(gt=0.0, le=360.0)] = 90.0
    range_m: PosFloat = 80.0
    rate_hz: PosFloat = 5.0
    phase_s: NonNeg = 0.0  # first capture time (s)
    processing_delay_ms: tuple[NonNeg, NonNeg] = (80.0, 120.0)  # uniform [min, max]
    position_error: list[ErrorBand] = Field(default_factory=_carom_bands, min_length=1)
    detection_probability: Probability = 0.95
    yaw_noise_std_rad: NonNeg = 0.05
    size_noise_std_m: NonNeg = 0.1
    min_visible_fraction: Probability = 0.3
    # The rendered camera of ``--rsu-source camera`` (sim.camera.rsu_camera); the noise model
    # above keeps its own fov. A wide sim fov (> 120 deg) needs image.fov_deg here.
    image: ImageConfig = Field(default_factory=ImageConfig)

    @field_validator("processing_delay_ms")
    @classmethod
    def _ordered(cls, value: tuple[float, float]) -> tuple[float, float]:
        if value[0] > value[1]:
            raise ValueError(f"[min, max] expected, got {list(value)}")
        return value

    @field_validator("position_error")
    @classmethod
    def _bands_sorted(cls, bands: list[ErrorBand]) -> list[ErrorBand]:
        edges = [b.max_range_m for b in bands]
        if edges != sorted(set(edges)):
            raise ValueError(f"max_range_m must strictly increase, got {edges}")
        return bands


class Mount(_Frozen):
    """Sensor position in the ego's base_link (m)."""

    x: Finite = 0.0
    y: Finite = 0.0
    z: Finite = 1.9


class LidarConfig(_Frozen):
    """On-board LiDAR + 3-D detector (CenterPoint-like)."""

    rate_hz: PosFloat = 10.0
    phase_s: NonNeg = 0.0
    range_m: PosFloat = 100.0
    mount: Mount = Field(default_factory=Mount)
    position_noise_std_m: NonNeg = 0.1
    yaw_noise_std_rad: NonNeg = 0.03
    size_noise_std_m: NonNeg = 0.05
    velocity_noise_std_mps: NonNeg = 0.3
    detection_probability: Probability = 0.98
    min_visible_fraction: Probability = 0.3


class VehicleCameraConfig(_Frozen):
    """On-board camera of the ego (image-level fusion, ``--fusion roif``)."""

    rate_hz: PosFloat = 10.0
    mount: Mount = Field(default_factory=lambda: Mount(x=1.5, y=0.0, z=1.4))
    image: ImageConfig = Field(default_factory=lambda: ImageConfig(yaw_deg=0.0, pitch_deg=0.0, fov_deg=90.0))


class LocalizationConfig(_Frozen):
    x_std_m: NonNeg = 0.05
    y_std_m: NonNeg = 0.05
    yaw_std_rad: NonNeg = 0.005
    # Localisation errors drift slowly (a first-order Gauss-Markov process), they are not
    # white: 0 gives independent errors per sample.
    correlation_time_s: NonNeg = 5.0


class Scenario(_Frozen):
    name: str = Field(min_length=1)
    description: str = ""
    duration_s: PosFloat
    target: str  # name of the actor scored as "the target"
    ego: Body
    actors: list[Body] = Field(min_length=1)
    buildings: list[Building] = Field(default_factory=list)
    rsu: RsuCameraConfig
    lidar: LidarConfig = Field(default_factory=LidarConfig)
    ego_camera: VehicleCameraConfig | None = None
    localization: LocalizationConfig = Field(default_factory=LocalizationConfig)

    @model_validator(mode="after")
    def _names(self) -> "Scenario":
        names = [self.ego.name] + [a.name for a in self.actors]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"body names must be unique, repeated: {duplicates}")
        if self.target not in names[1:]:
            raise ValueError(f"target {self.target!r} is not an actor; actors: {names[1:]}")
        return self


def bundled_scenarios() -> list[str]:
    """Names of the scenarios shipped in ``sim/scenarios/*.yaml``, sorted."""
    return bundled_names("sim", "scenarios")


def load_scenario(name_or_path: str | Path) -> Scenario:
    """A bundled scenario by name (e.g. ``"red-light-runner"``) or a YAML file by path."""
    return load_bundled_or_file(Scenario, name_or_path, "sim", "scenarios", "scenario", ScenarioError)
