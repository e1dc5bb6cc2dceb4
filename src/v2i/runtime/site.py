"""The site a service is configured by (``Site``): its RSUs (ids, poses, frame rates, ranges), its
connected vehicles (ids, box sizes, LiDAR rates), the WGS84 origin of the ``map`` frame and an
optional Lanelet2 map; loaded from a ``site.yaml`` (``load_site``), or derived from a scenario,
which contains one (``v2i.sim.scenario_site``). Also the site map's lane predictor
(``lane_predictor``), loaded once per map file.

Frame ``map``: x east, y north, metres, its origin at ``origin`` (a local-cartesian projection
about it turns the Lanelet2 map's WGS84 coordinates into map x/y).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from schemas.keys import check_id
from v2i.core.files import FileMissing, FileRefused, MiB, check_regular
from v2i.runtime.config import ConfigError, read_yaml, validate

# A site file: at most 62 RSUs and 64 vehicles, ~10 kB; 1 MiB bounds a wrong path's cost.
SITE_LIMIT_BYTES = 1 * MiB

PosFloat = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]


class SiteError(ConfigError):
    """A site file that cannot be used; the message names the file and the bad field."""


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class MapOrigin(_Frozen):
    """WGS84 latitude and longitude (deg) of the ``map`` frame's origin."""

    lat_deg: Annotated[float, Field(ge=-90.0, le=90.0)]
    lon_deg: Annotated[float, Field(ge=-180.0, le=180.0)]


class Position(_Frozen):
    """A point in ``map`` (m)."""

    x: Finite
    y: Finite
    z: Finite = 0.0


class RsuSite(_Frozen):
    """One roadside unit: its id (``v2x/rsu/{id}/*``), where its sensor stands and looks, its frame
    rate and how far its perception reaches."""

    id: str
    position: Position  # the sensor, map frame (m)
    yaw_deg: Finite = 0.0  # its heading, counter-clockwise from +x (deg)
    rate_hz: PosFloat = 5.0  # sensor frames per second
    range_m: PosFloat = 80.0

    @field_validator("id")
    @classmethod
    def _valid_id(cls, v: str) -> str:
        return check_id(v)

    @property
    def xy(self) -> tuple[float, float]:
        return self.position.x, self.position.y


class VehicleSite(_Frozen):
    """One connected vehicle: its id (``v2x/obu/{id}/*``), its box and its LiDAR's frame rate (the
    OBU's cycle rate)."""

    id: str
    size_m: tuple[PosFloat, PosFloat, PosFloat]  # length, width, height (m)
    lidar_rate_hz: PosFloat = 10.0

    @field_validator("id")
    @classmethod
    def _valid_id(cls, v: str) -> str:
        return check_id(v)


class Site(_Frozen):
    name: str = Field(min_length=1)
    origin: MapOrigin
    rsus: list[RsuSite] = Field(default_factory=list, max_length=62)
    vehicles: list[VehicleSite] = Field(min_length=1, max_length=64)
    map: Path | None = None  # Lanelet2 OSM file (lane-following prediction and compensation)

    @field_validator("map")
    @classmethod
    def _map_exists(cls, path: Path | None) -> Path | None:
        if path is None:
            return None
        try:
            check_regular(path, None, "Lanelet2 map")  # its size: LanePredictor.from_osm, which reads it
        except FileMissing:
            raise ValueError(f"no Lanelet2 map file {path}") from None
        except FileRefused as exc:
            raise ValueError(str(exc)) from None
        return path

    @model_validator(mode="after")
    def _unique_ids(self) -> "Site":
        for kind, ids in (("RSU", [r.id for r in self.rsus]), ("vehicle", [v.id for v in self.vehicles])):
            repeated = sorted({i for i in ids if ids.count(i) > 1})
            if repeated:
                raise ValueError(f"{kind} ids must be unique, repeated: {repeated}")
        return self

    def rsu(self, rsu_id: str) -> RsuSite:
        """The RSU a service of id ``rsu_id`` runs: the RSU of that id, or the only RSU of a
        single-RSU site whatever the id (services name themselves freely); ValueError otherwise."""
        ids = [r.id for r in self.rsus]
        if rsu_id in ids:
            return self.rsus[ids.index(rsu_id)]
        if len(ids) == 1:
            return self.rsus[0]
        raise ValueError(f"site {self.name!r} has no RSU {rsu_id!r}; its RSUs: {ids}")

    def vehicle(self, vehicle_id: str) -> VehicleSite:
        """The vehicle of that id, else the site's first vehicle."""
        return next((v for v in self.vehicles if v.id == vehicle_id), self.vehicles[0])

    def rsu_positions(self) -> dict[str, tuple[float, float]]:
        """RSU id -> its map position (m)."""
        return {r.id: r.xy for r in self.rsus}


def check_site_or_scenario(config, service: str, site_sources: tuple[str, ...]) -> None:
    """ValueError unless ``config`` names at most one of a site and a scenario, and a site only with a
    source that needs no simulated world (``site_sources``)."""
    if config.site is None:
        return
    if "scenario" in config.model_fields_set:
        raise ValueError("give site (--site) or scenario (--scenario), not both: a scenario contains its site")
    if config.source not in site_sources:
        raise ValueError(f"source {config.source!r} simulates a scenario: with a site (--site) the {service} "
                         f"takes its input from {' or '.join(site_sources)} (--source)")


def load_site(path: str | Path) -> Site:
    """The site file at ``path``; its ``map`` is relative to the file's folder. SiteError naming the
    file and the bad field when it cannot be used."""
    data = read_yaml(path, "site", SiteError, limit_bytes=SITE_LIMIT_BYTES)
    if isinstance(data, dict) and isinstance(data.get("map"), str):
        data = {**data, "map": Path(path).parent / data["map"]}
    return validate(Site, data, f"site {path}", SiteError)


def lane_predictor(site: Site):
    """A ``v2i.fusion.lane_prediction.LanePredictor`` on the site's map, projected about its origin;
    loaded once per map file (its path, modification time and size; ~26 ms a load) and origin: a
    LanePredictor is read-only once built, so the RSUs and OBUs of a run, a restarted service and
    the runs of one process share it. ValueError when the site has no map."""
    if site.map is None:
        raise ValueError(f"site {site.name!r} has no Lanelet2 map (a site file names one as map:, a scenario "
                         "has <scenario>.osm beside its YAML)")
    stat = site.map.stat()
    return _loaded_lane_predictor(str(site.map), stat.st_mtime_ns, stat.st_size, site.origin.lat_deg,
                                  site.origin.lon_deg)


@lru_cache(maxsize=8)
def _loaded_lane_predictor(path: str, mtime_ns: int, size: int, lat_deg: float, lon_deg: float):
    """The predictor of the map at ``path`` as it was at (``mtime_ns``, ``size``)."""
    from v2i.fusion.lane_prediction import LanePredictor  # (Lanelet2: only where a map is read)

    return LanePredictor.from_osm(path, lat_deg, lon_deg)
