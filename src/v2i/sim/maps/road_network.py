"""Road networks of the bundled scenarios as lane specifications (pure numpy, no Lanelet2).

A lane is a centreline polyline in the scenario's map frame (x east, y north, metres) in its
driving direction, a width and the kinds of its two boundary lines. ``v2i.sim.maps.lanelet_build``
turns lanes into Lanelet2 lanelets whose boundaries are the centreline offset by +-width / 2;
lanelets whose boundaries meet at the same points become successors in the routing graph, and
lanes that share a boundary line become neighbours.

Four-way intersection (red-light-runner, dense-intersection), after the scenario headers:
2 lanes per direction, 3.5 m wide (centres +-1.75 inner, +-5.25 outer), box |x|, |y| <= 7,
stop lines 10 m out. Built for northbound traffic (coming from the south) and rotated by
90, 180 and 270 deg for the other three approaches. Per approach: two approach lanes up to
13.75 m out (where right turns start), the inner lane on to the box edge (7 m, where left
turns start), and four connectors through the box, as a real map has them whatever the actors
drive: outer lane straight and right (8.5 m arc about (13.75, -13.75)), inner lane straight and
left (8.75 m arc about (-7, -7)); then two exit lanes on the far leg.

Highway (highway-merge): eastbound lanes y = 1.875 / 5.625 / 9.375, westbound 16.625 / 20.375 /
24.125 (3.75 m), an on-ramp along the merging actors' path onto an acceleration lane
(y = -1.875, x = 305..520) and a taper lanelet (x = 520..580) that joins the right lane.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

# Boundary line kinds (mapped to Lanelet2 type/subtype in lanelet_build.LINE_ATTRIBUTES)
DASHED, SOLID, CENTRE, KERB, EDGE, VIRTUAL = "dashed", "solid", "centre", "kerb", "edge", "virtual"


@dataclass(frozen=True)
class LaneSpec:
    """One lanelet: centreline (K, 2) m in driving direction, width, boundary kinds.

    ``start_heading_rad`` / ``end_heading_rad`` fix the cross-section at that end (boundary
    points at centre +- width/2 along the normal of that heading) so that the lane meets its
    neighbours' end points exactly; ``None`` uses the end segment's own normal.
    """

    name: str
    centre: np.ndarray
    width_m: float
    left: str
    right: str
    subtype: str = "road"
    location: str = "urban"
    turn_direction: str | None = None
    start_heading_rad: float | None = None
    end_heading_rad: float | None = None


@dataclass(frozen=True)
class Signal:
    """A traffic light controlling ``lanes``: stop line (2, 2) m and light head (2, 3) m."""

    name: str
    stop_line: np.ndarray
    light: np.ndarray
    lanes: tuple[str, ...]


@dataclass(frozen=True)
class RoadNetwork:
    name: str
    lanes: tuple[LaneSpec, ...]
    signals: tuple[Signal, ...] = ()


def _normal(heading_rad: float) -> np.ndarray:
    """Left unit normal n = (-sin psi, cos psi)."""
    return np.array([-np.sin(heading_rad), np.cos(heading_rad)])


def lane_bounds(lane: LaneSpec) -> tuple[np.ndarray, np.ndarray]:
    """Left and right boundary polylines, each (K, 2) m, of a lane.

    Interior vertices use a miter join so that each boundary stays width/2 from every
    segment: offset m = (n_prev + n_next) / (1 + n_prev . n_next), |m| = 1 / cos(half turn).
    """
    c = np.asarray(lane.centre, dtype=float)
    seg = np.diff(c, axis=0)
    n_seg = np.stack([-seg[:, 1], seg[:, 0]], axis=1) / np.hypot(seg[:, 0], seg[:, 1])[:, None]
    m = np.empty_like(c)
    m[0] = n_seg[0] if lane.start_heading_rad is None else _normal(lane.start_heading_rad)
    m[-1] = n_seg[-1] if lane.end_heading_rad is None else _normal(lane.end_heading_rad)
    dots = np.sum(n_seg[:-1] * n_seg[1:], axis=1)
    m[1:-1] = (n_seg[:-1] + n_seg[1:]) / (1.0 + dots)[:, None]
    half = 0.5 * lane.width_m
    return c + half * m, c - half * m


# ---------------------------------------------------------------- four-way intersection
LANE_W = 3.5
INNER_X, OUTER_X = 1.75, 5.25
BOX_M = 7.0  # kerb line of the crossing road: the box is |x|, |y| <= 7
RIGHT_START_M = 13.75  # right turns: r = 8.5 about (13.75, -13.75), from y = -13.75 to x = 13.75
RIGHT_R, LEFT_R = 8.5, 8.75  # left turns: r = 8.75 about (-7, -7), box edge to box edge
STOP_LINE_M = 10.0
ARC_STEP_RAD = np.deg2rad(5.0)
NORTH = np.pi / 2
APPROACHES = ("nb", "wb", "sb", "eb")  # canonical northbound rotated by 0, 90, 180, 270 deg


def arc(centre_xy, radius_m: float, a0_rad: float, a1_rad: float, step_rad: float = ARC_STEP_RAD) -> np.ndarray:
    """Points (K, 2) on a circle from polar angle a0 to a1, about ``step_rad`` apart."""
    n = max(int(np.ceil(abs(a1_rad - a0_rad) / step_rad)), 1)
    a = np.linspace(a0_rad, a1_rad, n + 1)
    return np.asarray(centre_xy, dtype=float) + radius_m * np.stack([np.cos(a), np.sin(a)], axis=1)


def _line(*points) -> np.ndarray:
    return np.asarray(points, dtype=float)


def _northbound_lanes(leg_m: float) -> list[LaneSpec]:
    """Lanes of traffic entering from the south (canonical approach, heading +y)."""
    o, i, r0, b = OUTER_X, INNER_X, RIGHT_START_M, BOX_M
    lane = LaneSpec
    return [
        lane("in-outer", _line((o, -leg_m), (o, -r0)), LANE_W, DASHED, KERB),
        lane("in-inner", _line((i, -leg_m), (i, -r0)), LANE_W, CENTRE, DASHED),
        lane("pre-inner", _line((i, -r0), (i, -b)), LANE_W, CENTRE, SOLID),
        lane("straight-outer", _line((o, -r0), (o, r0)), LANE_W, VIRTUAL, VIRTUAL, turn_direction="straight"),
        lane("right", arc((r0, -r0), RIGHT_R, np.pi, np.pi / 2), LANE_W, VIRTUAL, VIRTUAL,
             turn_direction="right", start_heading_rad=NORTH, end_heading_rad=0.0),
        lane("straight-inner", _line((i, -b), (i, b)), LANE_W, VIRTUAL, VIRTUAL, turn_direction="straight"),
        lane("left", arc((-b, -b), LEFT_R, 0.0, np.pi / 2), LANE_W, VIRTUAL, VIRTUAL,
             turn_direction="left", start_heading_rad=NORTH, end_heading_rad=np.pi),
        lane("out-inner-near", _line((i, b), (i, r0)), LANE_W, CENTRE, SOLID),
        lane("out-inner", _line((i, r0), (i, leg_m)), LANE_W, CENTRE, DASHED),
        lane("out-outer", _line((o, r0), (o, leg_m)), LANE_W, DASHED, KERB),
    ]


def _rotate(xy: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotate points (..., 2) about the origin: p' = R(angle) p."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.round(xy @ np.array([[c, s], [-s, c]]), 9)  # (R p^T)^T = p R^T; round away 1e-16 noise


def _rotated_lane(lane: LaneSpec, prefix: str, angle_rad: float) -> LaneSpec:
    def turn(h):
        return None if h is None else h + angle_rad

    return LaneSpec(
        f"{prefix}-{lane.name}", _rotate(lane.centre, angle_rad), lane.width_m, lane.left, lane.right,
        lane.subtype, lane.location, lane.turn_direction, turn(lane.start_heading_rad), turn(lane.end_heading_rad),
    )


def four_way_intersection(name: str, leg_m: float = 460.0) -> RoadNetwork:
    """The 4-way, 2+2-lane signalised intersection centred at the origin; legs ``leg_m`` long."""
    lanes, signals = [], []
    base = _northbound_lanes(leg_m)
    stop = _line((0.0, -STOP_LINE_M), (BOX_M, -STOP_LINE_M))
    # signal head 5 m up on the far side, over the outer lane, left to right as the driver sees it
    light = np.array([[OUTER_X - 0.25, STOP_LINE_M + 0.5, 5.0], [OUTER_X + 0.25, STOP_LINE_M + 0.5, 5.0]])
    for k, prefix in enumerate(APPROACHES):
        angle = k * np.pi / 2
        lanes += [_rotated_lane(lane, prefix, angle) for lane in base]
        light_xy = _rotate(light[:, :2], angle)
        signals.append(Signal(
            f"{prefix}-signal", _rotate(stop, angle), np.column_stack([light_xy, light[:, 2]]),
            tuple(f"{prefix}-{n}" for n in ("pre-inner", "straight-outer", "right")),
        ))
    return RoadNetwork(name, tuple(lanes), tuple(signals))


# ---------------------------------------------------------------- highway with on-ramp
HW_W = 3.75
HW_X0, HW_X1 = -1600.0, 2100.0
ACCEL_X0, ACCEL_X1, MERGE_X = 305.0, 520.0, 580.0
EB_Y = (1.875, 5.625, 9.375)  # right, middle, left
WB_Y = (16.625, 20.375, 24.125)  # left (median side), middle, right
ACCEL_Y = -1.875
RAMP = ((0.0, -83.25), (30.0, -75.0), (150.0, -42.0), (230.0, -20.0), (280.0, -8.0), (ACCEL_X0, ACCEL_Y))


def _eastbound(xs: tuple[float, ...]) -> list[LaneSpec]:
    """Three eastbound lanes in pieces between ``xs`` (``eb-right-0``, ...): neighbours share boundaries."""
    names, lanes = ("right", "middle", "left"), []
    for piece, (a, b) in enumerate(itertools.pairwise(xs)):
        for k, y in enumerate(EB_Y):
            left = EDGE if k == 2 else DASHED
            right = DASHED if (k == 0 and ACCEL_X0 <= a < MERGE_X) else (EDGE if k == 0 else DASHED)
            lanes.append(LaneSpec(f"eb-{names[k]}-{piece}", _line((a, y), (b, y)), HW_W, left, right,
                                  subtype="highway", location="nonurban"))
    return lanes


def highway_with_ramp(name: str) -> RoadNetwork:
    """Dual three-lane carriageway along x with an on-ramp, acceleration lane and taper."""
    lanes = _eastbound((HW_X0, ACCEL_X0, ACCEL_X1, MERGE_X, HW_X1))
    for k, y in enumerate(WB_Y):
        left = EDGE if k == 0 else DASHED
        right = EDGE if k == 2 else DASHED
        lanes.append(LaneSpec(f"wb-{('left', 'middle', 'right')[k]}", _line((HW_X1, y), (HW_X0, y)), HW_W,
                              left, right, subtype="highway", location="nonurban"))
    hw = {"subtype": "highway", "location": "nonurban"}
    lanes += [
        LaneSpec("ramp", _line(*RAMP), HW_W, EDGE, EDGE, end_heading_rad=0.0, **hw),
        LaneSpec("accel", _line((ACCEL_X0, ACCEL_Y), (ACCEL_X1, ACCEL_Y)), HW_W, DASHED, EDGE, **hw),
        # the taper's cross-sections stay vertical so that it meets both the acceleration lane
        # and the right lane's start at x = 580 point for point: a merge, two lanelets, one successor
        LaneSpec("taper", _line((ACCEL_X1, ACCEL_Y), (MERGE_X, EB_Y[0])), HW_W, VIRTUAL, EDGE,
                 start_heading_rad=0.0, end_heading_rad=0.0, **hw),
    ]
    return RoadNetwork(name, tuple(lanes))


NETWORKS = {
    "red-light-runner": lambda: four_way_intersection("red-light-runner"),
    "dense-intersection": lambda: four_way_intersection("dense-intersection"),
    "roif-intersection": lambda: four_way_intersection("roif-intersection"),
    "connected-intersection": lambda: four_way_intersection("connected-intersection"),
    "highway-merge": lambda: highway_with_ramp("highway-merge"),
}


def road_network(scenario: str) -> RoadNetwork:
    """The road network of a bundled scenario by name."""
    try:
        return NETWORKS[scenario]()
    except KeyError:
        raise ValueError(f"no road network for scenario {scenario!r}; one of {sorted(NETWORKS)}") from None
