"""Lanelet2 maps from ``RoadNetwork`` lane specs, and their OSM files.

Points are shared by coordinate (rounded to 1 mm) and boundary line strings by point sequence
(either direction), so that consecutive lanelets meet at the same points (successors in the
routing graph) and neighbouring lanelets share a boundary (lane changes across dashed lines;
opposite directions share the centre line inverted). Every lanelet carries its design centreline
as a custom ``centerline``, its lane name as the tag ``name`` and, on intersection connectors,
``turn_direction``. Ids are assigned in order from 1, so a rebuild writes the same file.

The OSM files use a local-cartesian projection about ``MAP_ORIGIN``: loaded with the same origin,
map x/y (m) equal the scenario's map frame (x east, y north).
"""

from __future__ import annotations

from pathlib import Path

import lanelet2
import numpy as np
from lanelet2.core import (
    AttributeMap,
    Lanelet,
    LaneletMap,
    LineString3d,
    Point3d,
    TrafficLight,
)
from lanelet2.io import Origin
from lanelet2.projection import LocalCartesianProjector

from v2i.core.files import check_regular
from v2i.fusion.lane_prediction import MAP_LIMIT_BYTES
from v2i.sim.maps import MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG
from v2i.sim.maps.road_network import (
    CENTRE,
    DASHED,
    EDGE,
    KERB,
    SOLID,
    VIRTUAL,
    LaneSpec,
    RoadNetwork,
    lane_bounds,
)

LINE_ATTRIBUTES = {
    DASHED: {"type": "line_thin", "subtype": "dashed"},
    SOLID: {"type": "line_thin", "subtype": "solid"},
    CENTRE: {"type": "line_thin", "subtype": "solid_solid"},
    KERB: {"type": "curbstone", "subtype": "high"},
    EDGE: {"type": "line_thick", "subtype": "solid"},
    VIRTUAL: {"type": "virtual"},
}


def projector(origin_lat_deg: float = MAP_ORIGIN_LAT_DEG, origin_lon_deg: float = MAP_ORIGIN_LON_DEG):
    """Local-cartesian projector: x east, y north (m) about the origin."""
    return LocalCartesianProjector(Origin(origin_lat_deg, origin_lon_deg))


class _Primitives:
    """Id counter plus shared points (by coordinate) and line strings (by point ids)."""

    def __init__(self) -> None:
        self._next = 0
        self._points: dict[tuple[float, float, float], Point3d] = {}
        self._lines: dict[tuple[int, ...], tuple[LineString3d, str]] = {}

    def new_id(self) -> int:
        self._next += 1
        return self._next

    def point(self, x: float, y: float, z: float = 0.0) -> Point3d:
        key = (round(float(x), 3), round(float(y), 3), round(float(z), 3))
        if key not in self._points:
            self._points[key] = Point3d(self.new_id(), *key)
        return self._points[key]

    def line(self, xy: np.ndarray, kind: str) -> LineString3d:
        """The boundary through ``xy`` (K, 2): shared if it exists in either direction."""
        pts = [self.point(x, y) for x, y in xy]
        key = tuple(p.id for p in pts)
        for k, inverted in ((key, False), (key[::-1], True)):
            if k in self._lines:
                line, existing = self._lines[k]
                if existing != kind:
                    raise ValueError(f"boundary {k} is both {existing!r} and {kind!r}")
                return line.invert() if inverted else line
        line = LineString3d(self.new_id(), pts, AttributeMap(LINE_ATTRIBUTES[kind]))
        self._lines[key] = (line, kind)
        return line

    def plain_line(self, xyz: np.ndarray, attributes: dict[str, str]) -> LineString3d:
        pts = [self.point(*p) for p in np.atleast_2d(xyz)]
        return LineString3d(self.new_id(), pts, AttributeMap(attributes))


def _lanelet(prims: _Primitives, lane: LaneSpec) -> Lanelet:
    left, right = lane_bounds(lane)
    attrs = {"type": "lanelet", "subtype": lane.subtype, "location": lane.location, "one_way": "yes",
             "name": lane.name}
    if lane.turn_direction is not None:
        attrs["turn_direction"] = lane.turn_direction
    ll = Lanelet(prims.new_id(), prims.line(left, lane.left), prims.line(right, lane.right), AttributeMap(attrs))
    ll.centerline = prims.plain_line(np.column_stack([lane.centre, np.zeros(len(lane.centre))]), {})
    return ll


def build_lanelet_map(network: RoadNetwork) -> LaneletMap:
    """A Lanelet2 map of the network: one lanelet per lane, one traffic light per signal."""
    prims = _Primitives()
    lanelets = {lane.name: _lanelet(prims, lane) for lane in network.lanes}
    for sig in network.signals:
        stop = prims.plain_line(np.column_stack([sig.stop_line, np.zeros(2)]), {"type": "stop_line"})
        head = prims.plain_line(sig.light, {"type": "traffic_light", "subtype": "red_yellow_green"})
        light = TrafficLight(prims.new_id(), AttributeMap({"name": sig.name}), [head], stop)
        for name in sig.lanes:
            lanelets[name].addRegulatoryElement(light)
    lmap = LaneletMap()  # add after the regulatory elements: the map takes what a lanelet refers to at add time
    for ll in lanelets.values():
        lmap.add(ll)
    return lmap


def write_map(network: RoadNetwork, path: str | Path) -> LaneletMap:
    """Build the network's map and write it as Lanelet2 OSM (local-cartesian about MAP_ORIGIN)."""
    lmap = build_lanelet_map(network)
    lanelet2.io.write(str(path), lmap, projector())
    return lmap


def load_map(path: str | Path) -> LaneletMap:
    """A Lanelet2 OSM file in the scenario map frame (projected about MAP_ORIGIN); a regular file of at
    most ``MAP_LIMIT_BYTES`` (FileRefused otherwise)."""
    check_regular(path, MAP_LIMIT_BYTES, "Lanelet2 map")
    return lanelet2.io.load(str(path), projector())
