"""The site a scenario contains (``v2i.runtime.site.Site``): its RSUs and vehicles as the services
see them, the scenarios' map origin and the scenario's Lanelet2 map, if it has one.

The bundled scenario YAMLs stay as they are; a service run on a scenario (``--scenario``) is
configured by this site, as one run on a site file (``--site``) is by that file's.
"""

from __future__ import annotations

from pathlib import Path

from v2i.runtime.site import MapOrigin, Position, RsuSite, Site, VehicleSite
from v2i.sim.maps import MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG, scenario_map
from v2i.sim.scenario import Scenario, load_scenario


def site_of(scenario: Scenario, map_path: Path | None = None) -> Site:
    """The site of ``scenario``: its RSU cameras' ids, poses, rates and ranges; its vehicles' names,
    sizes and LiDAR rates; the map origin of every scenario; ``map_path`` as its map."""
    return Site(
        name=scenario.name,
        origin=MapOrigin(lat_deg=MAP_ORIGIN_LAT_DEG, lon_deg=MAP_ORIGIN_LON_DEG),
        rsus=[RsuSite(id=r.id, position=Position(x=r.position.x, y=r.position.y, z=r.position.z),
                      yaw_deg=r.yaw_deg, rate_hz=r.rate_hz, range_m=r.range_m) for r in scenario.rsus],
        vehicles=[VehicleSite(id=v.name, size_m=v.size, lidar_rate_hz=v.lidar.rate_hz) for v in scenario.vehicles],
        map=map_path,
    )


def scenario_site(name_or_path: str | Path) -> Site:
    """The site of a bundled scenario by name or a scenario YAML by path, with its map
    (``v2i.sim.maps.scenario_map``)."""
    return site_of(load_scenario(name_or_path), scenario_map(str(name_or_path)))
