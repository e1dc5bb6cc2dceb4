"""Scenarios as data: frozen pydantic models of a YAML scenario file.

A scenario is a ground-truth world (ego, actors, static buildings) plus the sensor models
that observe it (roadside camera, on-board LiDAR, localisation). Frame ``map``: x east,
y north, metres; angles in the YAML are degrees where named ``*_deg``, radians otherwise.

Trajectory model: a polyline ``path`` in map (m), its corners optionally rounded by circular
arcs of ``corner_radius_m``, and a speed profile, either by time ``speed: [[t_s, mps], ...]``
(piecewise linear in time, constant before the first and after the last key) or by distance
along the path ``speed_at_m: [[s_m, mps], ...]`` (constant acceleration between keys, so it
converts exactly to time keys: t_{k+1} = t_k + 2 (s_{k+1} - s_k) / (v_k + v_{k+1})); see
``v2i.sim.world`` for the kinematics. An actor may exist only from ``spawn_s`` to ``despawn_s``;
its trajectory's clock starts at ``spawn_s``.

A site has RSUs (``rsus:``, each a roadside camera with its id, pose, rate, delay and an
optional link profile) and connected vehicles (``vehicles:``, the first one the ego, each
with its own LiDAR, localisation and camera). The single-RSU, single-vehicle form of older
files (``rsu:``, ``ego:``, ``lidar:``, ``localization:``, ``ego_camera:``) still loads: it is
read as one-element ``rsus`` and ``vehicles``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from shapely.geometry import Polygon
from shapely.validation import explain_validity

from schemas.classes import ObjectClass
from v2i.core.files import MiB
from v2i.runtime.config import ConfigError, bundled_names, load_bundled_or_file

from v2i.sim.paths import rounded_path, speed_keys_from_distance

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
    """Polyline path (map, m), corners rounded by ``corner_radius_m``, and a speed profile by time
    ([[t_s, mps], ...]) or by distance along the path ([[s_m, mps], ...]); single point = static."""

    path: list[tuple[Finite, Finite]] = Field(min_length=1)
    speed: list[tuple[Finite, NonNeg]] = Field(default_factory=lambda: [(0.0, 0.0)], min_length=1)
    speed_at_m: list[tuple[NonNeg, NonNeg]] | None = Field(default=None, min_length=1)
    corner_radius_m: PosFloat | None = None
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
    def _consistent(self) -> "Trajectory":
        if self.yaw_deg is not None and len(self.path) > 1:
            raise ValueError("yaw_deg is only for a single-point (static) path; a path's heading is its tangent")
        if self.speed_at_m is not None:
            if "speed" in self.model_fields_set:
                raise ValueError("give 'speed' (by time) or 'speed_at_m' (by distance), not both")
            speed_keys_from_distance(self.speed_at_m)  # raises when the body could never get there
        if self.corner_radius_m is not None:
            rounded_path(self.path, self.corner_radius_m)  # raises when a corner's arc does not fit
        return self

    def time_keys(self) -> list[Point2]:
        """The speed profile by time [[t_s, mps], ...] (``speed_at_m`` converted)."""
        return self.speed if self.speed_at_m is None else speed_keys_from_distance(self.speed_at_m)

    def points(self) -> list[Point2]:
        """The path the body follows: ``path`` with its corners rounded (``rounded_path``)."""
        return self.path if self.corner_radius_m is None else rounded_path(self.path, self.corner_radius_m)

    @property
    def is_static(self) -> bool:
        return len(self.path) == 1


class Body(_Frozen):
    """A vehicle or an actor: a named box of a class following a trajectory. An actor exists
    from ``spawn_s`` until ``despawn_s`` (scenario time); its trajectory's clock starts at
    ``spawn_s`` (speed key t = 0 is the moment it appears)."""

    name: str = Field(min_length=1)
    cls: ObjectClass = Field(alias="class")
    size: tuple[PosFloat, PosFloat, PosFloat]  # length, width, height (m)
    trajectory: Trajectory
    spawn_s: NonNeg = 0.0
    despawn_s: PosFloat | None = None

    @field_validator("cls", mode="before")
    @classmethod
    def _parse_class(cls, value: Any) -> ObjectClass:
        return ObjectClass.parse(value)

    @model_validator(mode="after")
    def _lifetime(self) -> "Body":
        if self.despawn_s is not None and self.despawn_s <= self.spawn_s:
            raise ValueError(f"despawn_s ({self.despawn_s}) must come after spawn_s ({self.spawn_s})")
        return self


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
    # CAROM (CARs On the Map; Saravanan et al. Sec. I): ~0.8 m within 50 m of the camera, ~1.7 m from 50 to 120 m
    return [ErrorBand(max_range_m=50.0, mean_error_m=0.8), ErrorBand(max_range_m=120.0, mean_error_m=1.7)]


class ImageConfig(_Frozen):
    """The physical camera behind an image source: what ``v2i.sim.camera`` renders and the
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
    # (``v2i.sim.camera.Sway``). None: the mount's default (an RSU pole RSU_SWAY_DEG, a vehicle 0).
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
    # The rendered camera of ``--rsu-source camera`` (v2i.sim.camera.rsu_camera); the noise model
    # above keeps its own fov. A wide sim fov (> 120 deg) needs image.fov_deg here.
    image: ImageConfig = Field(default_factory=ImageConfig)
    # The link between this RSU and each vehicle (a bundled profile name or a YAML path);
    # None: the run's profile (``--profile``).
    link_profile: str | None = None

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


class VehicleSpec(Body):
    """A connected vehicle: a body that runs an OBU with its own LiDAR, localisation and
    (optional) camera. Vehicles exist for the whole run (no spawn / despawn)."""

    lidar: LidarConfig = Field(default_factory=LidarConfig)
    localization: LocalizationConfig = Field(default_factory=LocalizationConfig)
    ego_camera: VehicleCameraConfig | None = None

    @model_validator(mode="after")
    def _always_there(self) -> "VehicleSpec":
        if self.spawn_s != 0.0 or self.despawn_s is not None:
            raise ValueError("a vehicle runs an OBU for the whole run: spawn_s / despawn_s are for actors")
        return self


# A scenario file: the densest bundled one is 28 kB; 4 MiB holds thousands of actors and waypoints.
SCENARIO_LIMIT_BYTES = 4 * MiB
_SINGLE_VEHICLE_KEYS = ("lidar", "localization", "ego_camera")


def _migrate_single(data: Any) -> Any:
    """The older single-RSU, single-vehicle layout read as one-element ``rsus`` / ``vehicles``."""
    if not isinstance(data, dict):
        return data
    data = dict(data)
    if "rsu" in data:
        if "rsus" in data:
            raise ValueError("give 'rsus' (a list) or the older 'rsu' (one), not both")
        data["rsus"] = [data.pop("rsu")]
    sensors = {k: data.pop(k) for k in _SINGLE_VEHICLE_KEYS if k in data}
    if "ego" in data:
        if "vehicles" in data:
            raise ValueError("give 'vehicles' (a list, the first is the ego) or the older 'ego', not both")
        ego = data.pop("ego")
        data["vehicles"] = [{**ego, **sensors} if isinstance(ego, dict) else ego]
    elif sensors:
        raise ValueError(f"{sorted(sensors)} belong to a vehicle: put them under its entry in 'vehicles'")
    return data


class V2vConfig(_Frozen):
    """V2V between the connected vehicles (``v2v: true``, or a block with these fields): each
    vehicle shares the objects its own sensors perceive with every other vehicle, through a
    channel of its own per ordered vehicle pair (sender -> receiver: this profile's downlink
    direction, at the distance between the two vehicles); see ``obu_service.peers``."""

    link_profile: str = "lte-v2x"  # PC5 sidelink: a bundled profile name or a YAML path
    max_peers: Annotated[int, Field(ge=1, le=32)] = 8  # peer slots (tracker source bits) per OBU


class Scenario(_Frozen):
    name: str = Field(min_length=1)
    description: str = ""
    duration_s: PosFloat
    target: str  # name of the actor scored as "the target"
    vehicles: list[VehicleSpec] = Field(min_length=1, max_length=64)  # the first one is the ego
    actors: list[Body] = Field(min_length=1)
    buildings: list[Building] = Field(default_factory=list)
    rsus: list[RsuCameraConfig] = Field(min_length=1, max_length=62)
    v2v: V2vConfig | None = None  # None (or ``v2v: false``): vehicles do not share with each other

    _migrate = model_validator(mode="before")(_migrate_single)

    @field_validator("v2v", mode="before")
    @classmethod
    def _v2v_switch(cls, value: Any) -> Any:
        """``v2v: true`` is the default block, ``v2v: false`` none."""
        if isinstance(value, bool):
            return {} if value else None
        return value

    @model_validator(mode="after")
    def _names(self) -> "Scenario":
        names = [v.name for v in self.vehicles] + [a.name for a in self.actors]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"body names must be unique, repeated: {duplicates}")
        actors = [a.name for a in self.actors]
        if self.target not in actors:
            raise ValueError(f"target {self.target!r} is not an actor; actors: {actors}")
        ids = [r.id for r in self.rsus]
        if len(set(ids)) != len(ids):
            raise ValueError(f"RSU ids must be unique, got {ids}")
        return self

    # the first RSU and the ego: the single-RSU, single-vehicle view older code reads
    @property
    def rsu(self) -> RsuCameraConfig:
        return self.rsus[0]

    @property
    def ego(self) -> VehicleSpec:
        return self.vehicles[0]

    @property
    def lidar(self) -> LidarConfig:
        return self.ego.lidar

    @property
    def localization(self) -> LocalizationConfig:
        return self.ego.localization

    @property
    def ego_camera(self) -> VehicleCameraConfig | None:
        return self.ego.ego_camera

    def rsu_by_id(self, rsu_id: str | None) -> RsuCameraConfig:
        """The RSU of that id (None: the first); ScenarioError naming the ids there are."""
        if rsu_id is None:
            return self.rsu
        for rsu in self.rsus:
            if rsu.id == rsu_id:
                return rsu
        raise ScenarioError(f"scenario {self.name!r} has no RSU {rsu_id!r}; its RSUs: {[r.id for r in self.rsus]}")

    def rsu_index(self, rsu_id: str) -> int:
        """Index in ``rsus`` of the RSU a service of id ``rsu_id`` runs: the RSU of that id, or
        the only RSU of a single-RSU scenario whatever the id (services name themselves freely)."""
        ids = [r.id for r in self.rsus]
        if rsu_id in ids:
            return ids.index(rsu_id)
        if len(ids) == 1:
            return 0
        raise ScenarioError(f"scenario {self.name!r} has no RSU {rsu_id!r}; its RSUs: {ids}")

    def vehicle(self, name: str | None) -> VehicleSpec:
        """The vehicle of that name (None: the ego); ScenarioError naming the vehicles there are."""
        if name is None:
            return self.ego
        for v in self.vehicles:
            if v.name == name:
                return v
        raise ScenarioError(f"scenario {self.name!r} has no vehicle {name!r}; its vehicles: "
                            f"{[v.name for v in self.vehicles]}")


def bundled_scenarios() -> list[str]:
    """Names of the scenarios shipped in ``sim/scenarios/*.yaml``, sorted."""
    return bundled_names("v2i.sim", "scenarios")


def load_scenario(name_or_path: str | Path) -> Scenario:
    """A bundled scenario by name (e.g. ``"red-light-runner"``) or a YAML file by path."""
    return load_bundled_or_file(Scenario, name_or_path, "v2i.sim", "scenarios", "scenario", ScenarioError,
                                limit_bytes=SCENARIO_LIMIT_BYTES)
