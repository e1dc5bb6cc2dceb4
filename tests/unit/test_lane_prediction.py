"""Lanelet2 maps of the bundled scenarios and lane-following prediction (v2i.fusion.lane_prediction)."""

from __future__ import annotations

import lanelet2
import numpy as np
import pytest

from v2i.core.frames import wrap_angle
from v2i.fusion.lane_prediction import (
    HEADING_BASE_M,
    LaneGeometry,
    LanePredictionConfig,
    LanePredictor,
    branch_priors,
    chain_frame,
    chain_points,
    lane_sequences,
    propagate_along,
)
from v2i.fusion.motion import predict_cv
from v2i.core.objects import ObjectArray
from schemas.classes import ObjectClass
from v2i.sim.maps import MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG, bundled_maps, map_path
from v2i.sim.maps.lanelet_build import load_map, write_map
from v2i.sim.maps.road_network import lane_bounds, road_network
from v2i.sim.scenario import bundled_scenarios, load_scenario
from v2i.sim.world import World

LANELET_COUNTS = {"red-light-runner": 40, "dense-intersection": 40, "highway-merge": 18}
CAR = int(ObjectClass.CAR)


def _objs(xy, vxy, yaw=None, cls=CAR, axy=None) -> ObjectArray:
    xy, vxy = np.atleast_2d(np.asarray(xy, float)), np.atleast_2d(np.asarray(vxy, float))
    n = len(xy)
    yaw = np.arctan2(vxy[:, 1], vxy[:, 0]) if yaw is None else np.broadcast_to(np.asarray(yaw, float), (n,)).copy()
    return ObjectArray(
        ids=np.arange(n, dtype=np.int64), cls=np.full(n, cls, dtype=np.int64), xy=xy, z=np.zeros(n),
        lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=yaw, vxy=vxy,
        axy=None if axy is None else np.atleast_2d(np.asarray(axy, float)),
    )


@pytest.fixture(scope="module")
def intersection() -> LanePredictor:
    return LanePredictor.from_osm(map_path("dense-intersection"), MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG)


@pytest.fixture(scope="module")
def highway() -> LanePredictor:
    return LanePredictor.from_osm(map_path("highway-merge"), MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG)


def _graph(lmap):
    rules = lanelet2.traffic_rules.create(lanelet2.traffic_rules.Locations.Germany,
                                          lanelet2.traffic_rules.Participants.Vehicle)
    return lanelet2.routing.RoutingGraph(lmap, rules)


# ------------------------------------------------------------------------------- maps as data
MAPLESS = {"two-rsu-corridor"}  # no road network designed for it yet: compensation 'lane' refuses it


def test_every_bundled_scenario_has_a_map():
    assert bundled_maps() == sorted(set(bundled_scenarios()) - MAPLESS)


@pytest.mark.parametrize("name", sorted(LANELET_COUNTS))
def test_map_loads_with_the_generated_lanelets_and_geometry(name):
    network, lmap = road_network(name), load_map(map_path(name))
    by_name = {ll.attributes["name"]: ll for ll in lmap.laneletLayer}
    assert len(by_name) == LANELET_COUNTS[name] == len(network.lanes)
    for lane in network.lanes:
        ll = by_name[lane.name]
        left, right = lane_bounds(lane)
        for got, want in ((ll.centerline, lane.centre), (ll.leftBound, left), (ll.rightBound, right)):
            got_xy = np.array([[p.x, p.y] for p in got])
            np.testing.assert_allclose(got_xy, want, atol=1e-3)  # local-cartesian: map x/y = scenario frame
    assert not _graph(lmap).checkValidity()


@pytest.mark.parametrize("name", sorted(LANELET_COUNTS))
def test_shipped_map_is_what_the_generator_writes(name, tmp_path):
    fresh = tmp_path / f"{name}.osm"
    write_map(road_network(name), fresh)
    assert fresh.read_bytes() == map_path(name).read_bytes(), "run tools/make_lanelet_maps.py"


def test_intersection_has_every_turn_and_the_signals():
    lmap = load_map(map_path("red-light-runner"))
    graph = _graph(lmap)
    by_name = {ll.attributes["name"]: ll for ll in lmap.laneletLayer}

    def succ(name):
        return {f.attributes["name"] for f in graph.following(by_name[name], False)}

    for a, right_exit, left_exit in (("nb", "eb", "wb"), ("eb", "sb", "nb"), ("sb", "wb", "eb"), ("wb", "nb", "sb")):
        assert succ(f"{a}-in-outer") == {f"{a}-straight-outer", f"{a}-right"}
        assert succ(f"{a}-pre-inner") == {f"{a}-straight-inner", f"{a}-left"}
        assert succ(f"{a}-right") == {f"{right_exit}-out-outer"}
        assert succ(f"{a}-left") == {f"{left_exit}-out-inner-near"}
        assert by_name[f"{a}-left"].attributes["turn_direction"] == "left"
        assert graph.left(by_name[f"{a}-in-outer"]).attributes["name"] == f"{a}-in-inner"  # lane change allowed
    lights = by_name["nb-pre-inner"].trafficLights()
    assert len(lights) == 1 and {round(p.y, 3) for p in lights[0].stopLine} == {-10.0}
    assert len(list(lmap.regulatoryElementLayer)) == 4


def test_highway_ramp_merges_into_the_right_lane():
    lmap = load_map(map_path("highway-merge"))
    graph = _graph(lmap)
    by_name = {ll.attributes["name"]: ll for ll in lmap.laneletLayer}
    assert [f.attributes["name"] for f in graph.following(by_name["ramp"], False)] == ["accel"]
    assert [f.attributes["name"] for f in graph.following(by_name["accel"], False)] == ["taper"]
    assert [f.attributes["name"] for f in graph.following(by_name["taper"], False)] == ["eb-right-3"]
    assert [f.attributes["name"] for f in graph.following(by_name["eb-right-2"], False)] == ["eb-right-3"]
    assert graph.left(by_name["accel"]).attributes["name"] == "eb-right-1"


@pytest.mark.parametrize("name", sorted(LANELET_COUNTS))
def test_road_users_drive_on_the_map(name):
    """Every vehicle of the scenario is matched to a lane, on its centreline, all run long
    (cyclists ride 1.35 m right of it; lane changes leave the centreline)."""
    pred = LanePredictor.from_osm(map_path(name), MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG)
    world = World(load_scenario(name))
    for t_s in np.arange(0.0, world.duration_s, 0.5):
        objs = world.actors_at(t_s)
        road = (objs.cls != int(ObjectClass.PEDESTRIAN)) & np.isin(objs.cls, pred.config.map_classes)
        on_road = road & (np.abs(objs.xy[:, 0]) < 2000) & (np.abs(objs.xy[:, 1]) < 400)
        parked = np.array([world.actor_names[int(i)].startswith("parked") for i in objs.ids])
        lane, _, d = pred.match(objs)
        assert np.all(lane[on_road & ~parked] >= 0), (t_s, objs.ids[on_road & ~parked & (lane < 0)])
        cyclist = objs.cls == int(ObjectClass.CYCLIST)
        changing = np.array([world.actor_names[int(i)] == "lane-changer" for i in objs.ids])
        assert np.all(np.abs(d[on_road & ~parked & ~cyclist & ~changing]) < 0.05)


# ------------------------------------------------------------------------------- prediction
def test_straight_lane_equals_cv(intersection, highway):
    objs = _objs([[5.25, -120.0], [5.9, -80.0], [-1.75, 150.0]], [[0.0, 12.0], [0.0, 9.0], [0.0, -13.9]])
    for dt_s in (0.1, 0.7, np.array([0.2, 1.0, 0.5])):
        got, want = intersection.predict_objects(objs, dt_s), predict_cv(objs, dt_s)
        np.testing.assert_allclose(got.xy, want.xy, atol=1e-9)
        np.testing.assert_allclose(got.vxy, want.vxy, atol=1e-6)  # map round trip: tangents to ~1e-9 rad
        np.testing.assert_allclose(got.yaw, want.yaw, atol=1e-8)
    traj = intersection.predict_trajectories(objs, 5.0, 0.1)
    t = 0.1 * np.arange(1, 51)
    np.testing.assert_allclose(traj[..., :2], objs.xy[:, None] + objs.vxy[:, None] * t[None, :, None], atol=1e-9)
    hw = _objs([[100.0, 5.625], [800.0, 20.375]], [[28.0, 0.0], [-27.0, 0.0]])
    np.testing.assert_allclose(highway.predict_objects(hw, 0.8).xy, predict_cv(hw, 0.8).xy, atol=1e-9)


def _left_turn_truth(t_s: np.ndarray, speed_mps: float, a0_rad: float) -> np.ndarray:
    """Northbound left turn: the arc r = 8.75 about (-7, -7) from polar angle a0, then west on y = 1.75."""
    r, centre = 8.75, np.array([-7.0, -7.0])
    a = a0_rad + speed_mps * t_s / r
    on_arc = centre + r * np.stack([np.cos(a), np.sin(a)], axis=1)
    past = speed_mps * t_s - r * (np.pi / 2 - a0_rad)  # metres beyond the arc's end (-7, 1.75)
    after = np.stack([-7.0 - past, np.full_like(past, 1.75)], axis=1)
    return np.where((past > 0)[:, None], after, on_arc)


def test_turning_connector_follows_the_curve(intersection):
    a0, v = np.deg2rad(15.0), 7.0
    start = _left_turn_truth(np.zeros(1), v, a0)[0]
    heading = a0 + np.pi / 2  # counter-clockwise tangent
    objs = _objs(start, v * np.array([np.cos(heading), np.sin(heading)]))
    t = 0.1 * np.arange(1, 31)
    truth = _left_turn_truth(t, v, a0)
    traj = intersection.predict_trajectories(objs, 3.0, 0.1)[0]
    err_map = np.hypot(*(traj[:, :2] - truth).T)
    err_cv = np.hypot(*(objs.xy + objs.vxy * t[:, None] - truth).T)
    assert err_map.max() < 0.1  # 5 deg chords vs the exact arc
    assert err_cv[9] > 2.0 and err_map[9] < 0.05 * err_cv[9]
    assert abs(wrap_angle(traj[-1, 2] - np.pi)) < 1e-6  # heading west after the turn
    one = intersection.predict_objects(objs, 1.0)
    np.testing.assert_allclose(one.xy[0], truth[9], atol=0.1)
    assert abs(wrap_angle(one.yaw[0] - np.arctan2(*(truth[10] - truth[8])[::-1]))) < np.deg2rad(1.0)
    assert abs(np.hypot(*one.vxy[0]) - v) < 1e-6


def test_lateral_offset_is_preserved(intersection):
    # right turn (clockwise about (13.75, -13.75), r = 8.5); 0.5 m left of the centreline = r + 0.5
    centre, a = np.array([13.75, -13.75]), np.deg2rad(160.0)
    xy = centre + 9.0 * np.array([np.cos(a), np.sin(a)])
    heading = a - np.pi / 2
    objs = _objs(xy, 5.0 * np.array([np.cos(heading), np.sin(heading)]))
    _, _, d0 = intersection.match(objs)
    assert d0[0] == pytest.approx(0.5, abs=0.02)
    traj = intersection.predict_trajectories(objs, 5.0, 0.1)[0]
    on_arc = traj[:, 0] < 13.75
    np.testing.assert_allclose(np.hypot(*(traj[on_arc, :2] - centre).T), 9.0, atol=0.03)
    np.testing.assert_allclose(traj[~on_arc, 1], -5.25 + 0.5, atol=0.03)  # eastbound exit, still 0.5 m left
    # straight lane: offset d kept, also through the box
    straight = _objs([[1.0, -40.0]], [[0.0, 13.0]])
    np.testing.assert_allclose(intersection.predict_trajectories(straight)[0, :, 0], 1.0, atol=1e-6)


def test_lateral_offset_decays_when_configured():
    pred = LanePredictor.from_osm(map_path("highway-merge"), MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG,
                                  LanePredictionConfig(lateral_decay_s=1.0))
    objs = _objs([[0.0, 5.625 + 1.0]], [[25.0, 0.0]])
    traj = pred.predict_trajectories(objs, 3.0, 0.5)[0]
    np.testing.assert_allclose(traj[:, 1] - 5.625, np.exp(-0.5 * np.arange(1, 7)), atol=1e-6)  # d0 e^(-t / tau)


def test_off_map_objects_fall_back_to_cv_exactly(intersection):
    objs = ObjectArray.concat([
        _objs([[5.25, -40.0]], [[0.0, 1.4]], cls=int(ObjectClass.PEDESTRIAN)),  # pedestrian on a lane
        _objs([[30.0, 30.0]], [[3.0, 2.0]]),  # car inside a corner block
        _objs([[5.25, -40.0]], [[0.0, -10.0]]),  # wrong way on the northbound lane
        _objs([[-40.0, -5.25]], [[0.0, 4.0]]),  # crossing the eastbound lanes
        _objs([[1.75, -40.0]], [[0.0, 10.0]], cls=int(ObjectClass.UNKNOWN)),
    ])
    objs = objs.with_(axy=np.tile([0.5, -0.3], (len(objs), 1)))  # CV ignores it: CA would not
    lane, _, _ = intersection.match(objs)
    assert np.all(lane == -1)
    for dt_s in (0.3, np.linspace(0.1, 1.0, len(objs))):
        got, want = intersection.predict_objects(objs, dt_s), predict_cv(objs, dt_s)
        for f in ("xy", "yaw", "vxy", "axy", "age_s"):
            np.testing.assert_array_equal(getattr(got, f), getattr(want, f))
    traj = intersection.predict_trajectories(objs, 2.0, 0.5)
    t = np.array([0.5, 1.0, 1.5, 2.0])
    np.testing.assert_array_equal(traj[..., :2], objs.xy[:, None] + objs.vxy[:, None] * t[None, :, None])
    np.testing.assert_array_equal(traj[..., 2], np.repeat(objs.yaw[:, None], 4, axis=1))


def _match_every_pair(pred: LanePredictor, objs: ObjectArray):
    """LanePredictor.match as it was: the cost of every (object, segment) pair as (N, S) arrays."""
    cfg, seg = pred.config, pred._seg
    n = len(objs)
    moving = np.hypot(objs.vxy[:, 0], objs.vxy[:, 1]) > cfg.min_speed_for_heading_mps
    heading = np.where(moving, np.arctan2(objs.vxy[:, 1], objs.vxy[:, 0]), objs.yaw)
    rel = objs.xy[:, None, :] - seg.a[None]  # (N, S, 2)
    along = rel[..., 0] * seg.t[:, 0] + rel[..., 1] * seg.t[:, 1]
    lateral = seg.t[:, 0] * rel[..., 1] - seg.t[:, 1] * rel[..., 0]
    dist = np.hypot(along - np.clip(along, 0.0, seg.length), lateral)
    half_w = np.where(lateral >= 0.0, seg.half_w[:, 0], seg.half_w[:, 1])
    dpsi = wrap_angle(heading[:, None] - seg.psi)
    ok = (dist <= half_w + cfg.lateral_margin_m) & (np.abs(dpsi) <= cfg.heading_tolerance_rad)
    ok &= ~(seg.first & (along < -1e-6)) & ~(seg.last & (along > seg.length + 1e-6))
    ok &= np.isin(objs.cls, pred._map_classes)[:, None]
    cost = np.where(ok, (dist / half_w) ** 2 + (dpsi / cfg.heading_scale_rad) ** 2, np.inf)
    best = np.argmin(cost, axis=1)
    rows = np.arange(n)
    matched = np.isfinite(cost[rows, best])
    lane = np.where(matched, seg.lane[best], -1)
    s0 = seg.s0[best] + np.clip(along[rows, best], 0.0, seg.length[best])
    return lane, np.where(matched, s0, 0.0), np.where(matched, lateral[rows, best], 0.0)


@pytest.mark.parametrize("name", ["dense-intersection", "highway-merge"])
def test_match_over_candidate_pairs_equals_every_pair(name, intersection, highway):
    """match scores only the pairs near a segment's midpoint: lanes, s0 and d0 equal, as bytes,
    those of every pair's cost, for objects on lanes, beside them, off the map, of every class,
    moving or not, at and around lane ends; none, one or many at once."""
    pred = intersection if name == "dense-intersection" else highway
    rng = np.random.default_rng(5)
    seg = pred._seg
    matched = 0
    for n in (0, 1, 2, 7, 40, 200):
        on = rng.integers(0, len(seg.lane), n)  # near a segment: anywhere along it, up to 4 m aside
        u = rng.uniform(-0.3, 1.3, n)[:, None]
        xy = seg.a[on] + u * seg.length[on, None] * seg.t[on] + rng.normal(0.0, 2.0, (n, 1)) * seg.t[on][:, ::-1] * [-1, 1]
        far = rng.random(n) < 0.2
        xy[far] = rng.uniform(-300.0, 300.0, (int(far.sum()), 2))
        speed = rng.choice([0.0, 0.2, 8.0], n)
        angle = seg.psi[on] + rng.normal(0.0, 0.6, n) + rng.choice([0.0, np.pi], n, p=[0.85, 0.15])
        objs = _objs(xy, speed[:, None] * np.column_stack([np.cos(angle), np.sin(angle)]),
                     yaw=seg.psi[on] + rng.normal(0.0, 0.6, n))
        objs = objs.with_(cls=rng.choice([int(c) for c in ObjectClass], n))
        got, want = pred.match(objs), _match_every_pair(pred, objs)
        for g, w in zip(got, want):
            assert g.dtype == w.dtype and g.shape == w.shape and g.tobytes() == w.tobytes()
        matched += int(np.count_nonzero(got[0] >= 0))
    assert matched > 50


def test_chain_frame_in_one_lookup_equals_three(intersection):
    """chain_frame looks the points at s, s + b and s - b up in one chain_points call: points and
    headings equal, as bytes, those of three calls (any chains, arc lengths past either end)."""
    chains = intersection._chains
    rng = np.random.default_rng(2)
    for p, t in ((1, 1), (5, 1), (17, 51), (3, 7)):
        chain = rng.integers(0, len(chains.first), p)
        s = rng.uniform(-20.0, 400.0, (p, t))
        points, psi = chain_frame(chains, chain, s)
        ahead = chain_points(chains, chain, s + HEADING_BASE_M)
        behind = chain_points(chains, chain, s - HEADING_BASE_M)
        want = np.arctan2(ahead[..., 1] - behind[..., 1], ahead[..., 0] - behind[..., 0])
        assert points.shape == (p, t, 2) and psi.shape == (p, t)
        assert np.ascontiguousarray(points).tobytes() == chain_points(chains, chain, s).tobytes()
        assert psi.tobytes() == want.tobytes()


def test_frenet_without_motion_gives_the_same_positions_and_yaws(intersection):
    """_frenet(..., motion=False) (the trajectories' call) leaves out vxy and dpsi only: xy and
    yaw equal, as bytes, those of the full call."""
    rng = np.random.default_rng(4)
    seg = intersection._seg
    on = rng.integers(0, len(seg.lane), 30)
    objs = _objs(seg.a[on] + rng.normal(0.0, 0.5, (30, 2)), 8.0 * np.column_stack([np.cos(seg.psi[on]), np.sin(seg.psi[on])]))
    lane, s0, d0 = intersection.match(objs)
    idx = np.flatnonzero(lane >= 0)
    assert len(idx) > 10
    args = (objs.take(idx), intersection._chains.of_lane[lane[idx], 0], s0[idx], d0[idx],
            np.broadcast_to(0.1 * np.arange(1, 51), (len(idx), 50)))
    full, lean = intersection._frenet(*args), intersection._frenet(*args, motion=False)
    assert set(lean) == {"xy", "yaw"} and set(full) == {"xy", "yaw", "vxy", "dpsi"}
    assert all(full[k].tobytes() == lean[k].tobytes() for k in ("xy", "yaw"))


def test_branch_hypotheses_straight_first(intersection):
    objs = _objs([[5.25, -20.0]], [[0.0, 10.0]])  # outer lane, 6 m before the right turn starts
    traj, prob = intersection.predict_hypotheses(objs, 5.0, 0.1)
    assert traj.shape == (1, 2, 50, 3) and prob.shape == (1, 2)
    assert prob[0, 0] > 0.9 and prob.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(traj[0, 0, -1, :2], [5.25, 30.0], atol=1e-9)  # straight on
    assert traj[0, 1, -1, 0] > 20.0 and traj[0, 1, -1, 1] == pytest.approx(-5.25, abs=1e-6)  # right turn, east
    np.testing.assert_array_equal(intersection.predict_trajectories(objs, 5.0, 0.1), traj[:, 0])


def test_branch_priors_and_sequences_on_plain_arrays():
    straight = np.array([[0.0, 0.0], [10.0, 0.0]])
    geometry = LaneGeometry(
        names=("in", "turn", "ahead"),
        centres=(straight, np.array([[10.0, 0.0], [15.0, 1.0], [18.0, 5.0], [19.0, 10.0]]), straight + [10.0, 0.0]),
        half_widths=tuple(np.full((k, 2), 1.75) for k in (1, 3, 1)),
        successors=((1, 2), (), ()),
    )
    priors = branch_priors(geometry, sigma_rad=1.0)
    np.testing.assert_allclose(priors[0], [0.2, 0.8], atol=0.01)  # 67 deg turn: exp(-1.18^2) = 0.25 vs 1
    seqs = lane_sequences(geometry, priors, 0, lookahead_m=50.0)
    assert [s for s, _ in seqs] == [(0, 2), (0, 1)] and sum(p for _, p in seqs) == pytest.approx(1.0)
    pred = LanePredictor(geometry)
    out = pred.predict_objects(_objs([[2.0, 0.3]], [[5.0, 0.0]]), 2.0)
    np.testing.assert_allclose(out.xy, [[12.0, 0.3]], atol=1e-12)


def test_constant_acceleration_stops_instead_of_reversing(intersection):
    s, v = propagate_along(np.array([0.0]), np.array([10.0]), np.array([-5.0]), np.array([[1.0, 2.0, 5.0]]), True)
    np.testing.assert_allclose(s[0], [7.5, 10.0, 10.0])
    np.testing.assert_allclose(v[0], [5.0, 0.0, 0.0])
    pred = LanePredictor(intersection.geometry, LanePredictionConfig(use_acceleration=True))
    objs = _objs([[5.25, -40.0]], [[0.0, 10.0]], axy=[[0.0, -5.0]])
    out = pred.predict_objects(objs, 4.0)
    np.testing.assert_allclose(out.xy, [[5.25, -30.0]], atol=1e-9)
    np.testing.assert_allclose(out.vxy, 0.0, atol=1e-12)
    np.testing.assert_allclose(out.axy, 0.0, atol=1e-12)


def test_shapes_and_no_nans_on_scenario_ground_truth(intersection, highway):
    for pred, name in ((intersection, "dense-intersection"), (highway, "highway-merge")):
        world = World(load_scenario(name))
        for t_s in (0.0, 10.4, 16.8, 29.9):
            objs = world.actors_at(t_s)
            traj = pred.predict_trajectories(objs, 5.0, 0.1)
            hyp, prob = pred.predict_hypotheses(objs, 2.0, 0.25)
            out = pred.predict_objects(objs, 0.35)
            assert traj.shape == (len(objs), 50, 3)
            assert hyp.shape[:1] + hyp.shape[2:] == (len(objs), 8, 3) and prob.shape == hyp.shape[:2]
            np.testing.assert_allclose(prob.sum(axis=1), 1.0)
            assert len(out) == len(objs) and np.array_equal(out.ids, objs.ids)
            for arr in (traj, hyp, prob, out.xy, out.yaw, out.vxy, out.axy):
                assert np.all(np.isfinite(arr))
    empty = ObjectArray.empty()
    assert intersection.predict_trajectories(empty, 1.0, 0.1).shape == (0, 10, 3)
    assert len(intersection.predict_objects(empty, 0.5)) == 0


@pytest.mark.parametrize("name", ["dense-intersection", "highway-merge"])
def test_trajectories_without_probabilities_equal_the_full_call(name, intersection, highway):
    """predict_trajectories (``_trajectories(..., probabilities=False)``: no probabilities, no repeat of
    missing hypotheses for one) gives, as bytes, the first hypothesis of the full call with one and
    with every hypothesis; objects on lanes, off the map, of every class, none, one or many."""
    pred = intersection if name == "dense-intersection" else highway
    rng = np.random.default_rng(8)
    seg = pred._seg
    for n in (0, 1, 3, 9, 60):
        on = rng.integers(0, len(seg.lane), n)
        xy = seg.a[on] + rng.uniform(0.0, 1.0, (n, 1)) * seg.length[on, None] * seg.t[on] + rng.normal(0.0, 1.0, (n, 2))
        far = rng.random(n) < 0.2
        xy[far] = rng.uniform(-300.0, 300.0, (int(far.sum()), 2))
        vxy = rng.choice([0.0, 9.0], (n, 1)) * np.column_stack([np.cos(seg.psi[on]), np.sin(seg.psi[on])])
        objs = _objs(xy, vxy, yaw=seg.psi[on]).with_(cls=rng.choice([int(c) for c in ObjectClass], n))
        got = pred.predict_trajectories(objs, 5.0, 0.1)
        one, prob_one = pred._trajectories(objs, 5.0, 0.1, 1)
        every, _ = pred._trajectories(objs, 5.0, 0.1, pred.config.max_hypotheses)
        assert got.shape == (n, 50, 3) and prob_one.shape == (n, 1)
        assert got.tobytes() == np.ascontiguousarray(one[:, 0]).tobytes() == np.ascontiguousarray(every[:, 0]).tobytes()
