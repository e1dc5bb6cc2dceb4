"""Simulated world: scenario loading, kinematics, occlusion, sensor models."""

from __future__ import annotations

from importlib.resources import files

import numpy as np
import pytest
import yaml
from shapely.geometry import LineString, Polygon

from v2i.core.frames import map_to_base_points
from v2i.core.objects import ObjectArray
from schemas.classes import ObjectClass
from v2i.sim.occlusion import box_points, segments_hit_boxes, segments_hit_polygons, visible_fraction
from v2i.sim.scenario import Scenario, ScenarioError, bundled_scenarios, load_scenario
from v2i.sim.sensors import Lidar, Localization, RsuCamera, frame_times, mean_error_at
from v2i.sim.world import Trajectories, World

RLR = "red-light-runner"


def _car(name: str, path, speed=None, yaw_deg=None, cls: str = "car") -> dict:
    traj: dict = {"path": path}
    if speed is not None:
        traj["speed"] = speed
    if yaw_deg is not None:
        traj["yaw_deg"] = yaw_deg
    return {"name": name, "class": cls, "size": [4.0, 2.0, 1.6], "trajectory": traj}


def _open_field(actors: list[dict], **sections) -> dict:
    """A minimal scenario dict: ego at the origin facing +x, camera at the origin facing +x."""
    data = {
        "name": "test", "duration_s": 10.0, "target": actors[0]["name"],
        "ego": _car("ego", [[0.0, 0.0]], yaw_deg=0.0),
        "actors": actors,
        "rsu": {"id": "rsu-t", "position": {"x": 0.0, "y": 0.0, "z": 7.0}, "yaw_deg": 0.0, "fov_deg": 90.0,
                "range_m": 80.0, "detection_probability": 1.0},
        "lidar": {"detection_probability": 1.0, "mount": {"x": 0.0, "y": 0.0, "z": 1.9}},
    }
    data.update(sections)
    return data


def _rlr_dict() -> dict:
    return yaml.safe_load((files("v2i.sim") / "scenarios" / f"{RLR}.yaml").read_text())


# --- scenario loading -------------------------------------------------------------------

def test_load_bundled_by_name_and_by_path(tmp_path):
    assert RLR in bundled_scenarios()
    sc = load_scenario(RLR)
    assert sc.name == RLR and sc.target == "adversary" and sc.duration_s == 30.0
    assert sc.actors[0].cls is ObjectClass.CAR and sc.rsu.rate_hz == 5.0 and sc.lidar.rate_hz == 10.0
    file = tmp_path / "copy.yaml"
    file.write_text(yaml.safe_dump(_rlr_dict()))
    assert load_scenario(str(file)) == sc


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda d: d["actors"][1].update(size=[5.9, -2.0, 2.6]), "actors.1.size"),
        (lambda d: d["lidar"].update(range_mm=100), "vehicles.0.lidar.range_mm"),  # the older layout, migrated
        (lambda d: d["actors"][0].update({"class": "spaceship"}), "actors.0.class"),
        (lambda d: d["actors"][0]["trajectory"].update(speed=[[2.0, 1.0], [1.0, 2.0]]), "actors.0.trajectory.speed"),
        (lambda d: d["rsu"].update(processing_delay_ms=[120, 80]), "rsus.0.processing_delay_ms"),
    ],
)
def test_bad_field_is_named(tmp_path, edit, field):
    data = _rlr_dict()
    edit(data)
    file = tmp_path / "bad.yaml"
    file.write_text(yaml.safe_dump(data))
    with pytest.raises(ScenarioError, match=field.replace(".", r"\.")):
        load_scenario(file)


def test_unknown_target_and_unknown_name():
    data = _rlr_dict()
    data["target"] = "ghost"
    with pytest.raises(Exception, match="ghost"):
        Scenario.model_validate(data)
    with pytest.raises(ScenarioError, match=RLR) as err:
        load_scenario("no-such-scenario")
    assert "no-such-scenario" in str(err.value)


# --- kinematics -------------------------------------------------------------------------

def test_trajectory_kinematics_accelerating_l_path():
    # v: 0 -> 4 m/s over 2 s (a = 2), then 4 m/s; path 10 m east then 10 m north (L = 20 m)
    mover = _car("m", [[0, 0], [10, 0], [10, 10]], speed=[[0, 0], [2, 4]])
    world = World(Scenario.model_validate(_open_field([mover])))
    gt = world.actors_at(1.0)  # s = a t^2 / 2 = 1
    np.testing.assert_allclose(gt.xy[0], [1, 0], atol=1e-12)
    np.testing.assert_allclose(gt.vxy[0], [2, 0], atol=1e-12)
    np.testing.assert_allclose(gt.axy[0], [2, 0], atol=1e-12)
    gt = world.actors_at(4.0)  # s = 4 + 4 * 2 = 12: 2 m up the second leg
    np.testing.assert_allclose(gt.xy[0], [10, 2], atol=1e-12)
    np.testing.assert_allclose(gt.vxy[0], [0, 4], atol=1e-12)
    np.testing.assert_allclose(gt.axy[0], [0, 0], atol=1e-12)
    assert gt.yaw[0] == pytest.approx(np.pi / 2)
    gt = world.actors_at(7.0)  # s = 24 > L: stopped at the end, heading kept
    np.testing.assert_allclose(gt.xy[0], [10, 10], atol=1e-12)
    np.testing.assert_allclose(gt.vxy[0], [0, 0])
    assert gt.yaw[0] == pytest.approx(np.pi / 2)


def test_speed_constant_before_first_key_and_static_actors():
    late = _car("late", [[0, 0], [100, 0]], speed=[[1.0, 2.0], [3.0, 4.0]])
    parked = _car("parked", [[5.0, -3.0]], yaw_deg=30.0)
    world = World(Scenario.model_validate(_open_field([late, parked])))
    assert world.actors_at(0.5).xy[0, 0] == pytest.approx(1.0)  # 2 m/s before the first key
    assert world.actors_at(2.0).xy[0, 0] == pytest.approx(2.0 + 2.0 + 0.5)  # + v t + a t^2 / 2
    assert world.actors_at(5.0).xy[0, 0] == pytest.approx(2.0 + 6.0 + 8.0)  # 4 m/s after the last
    for t in (0.0, 3.3, 9.0):
        gt = world.actors_at(t)
        np.testing.assert_allclose(gt.xy[1], [5, -3])
        assert gt.yaw[1] == pytest.approx(np.deg2rad(30.0)) and not gt.vxy[1].any()


def test_world_red_light_runner_ground_truth():
    world = World(load_scenario(RLR))
    assert list(world.actor_names) == list(range(1, len(world.actor_names) + 1))
    assert world.actor_names[world.target_id] == "adversary"
    gt = world.actors_at(10.0)
    k = world.target_id - 1
    np.testing.assert_allclose(gt.xy[k], [-150 + 139.0, -1.75])
    np.testing.assert_allclose(gt.vxy[k], [13.9, 0.0])
    np.testing.assert_allclose(gt.z, gt.lwh[:, 2] / 2)
    assert (gt.sources == 0).all() and (gt.confidence == 1).all()
    ego = world.ego_at(10.0)
    assert (ego.x, ego.y, ego.yaw, ego.vx, ego.vy) == pytest.approx((5.25, -12.35, np.pi / 2, 0, 0))
    np.testing.assert_allclose(world.ego_size, [4.7, 1.85, 1.5])


@pytest.mark.parametrize("name", sorted(bundled_scenarios()))
def test_ego_xy_at_is_ego_at_s_position_bit_for_bit(name):
    scenario = load_scenario(name)
    for vehicle in [None] + [v.name for v in scenario.vehicles]:
        world = World(scenario, vehicle) if vehicle else World(scenario)
        for t in np.concatenate([[-1.0, 0.0, -0.0], np.linspace(0.0, scenario.duration_s + 2.0, 97)]):
            ego = world.ego_at(t)
            assert world.ego_xy_at(t) == (ego.x, ego.y)
    with pytest.raises(ValueError, match="no ego"):
        World(scenario, site=True).ego_xy_at(0.0)


# --- occlusion vs shapely ---------------------------------------------------------------

def _box_polygon(box) -> Polygon:
    pts = box_points(np.array([box[:2]]), np.array([box[2:4]]), np.array([box[4]]), samples=5)[0, 1:]
    return Polygon(pts)


def _star_polygon(rng, centre, n=7) -> np.ndarray:
    ang = np.sort(rng.uniform(0, 2 * np.pi, n))
    rad = rng.uniform(1.0, 6.0, n)  # non-convex in general, always simple
    return centre + np.column_stack([rad * np.cos(ang), rad * np.sin(ang)])


def test_segments_vs_boxes_and_polygons_match_shapely():
    rng = np.random.default_rng(7)
    a, b = rng.uniform(-30, 30, (300, 2)), rng.uniform(-30, 30, (300, 2))
    boxes = np.column_stack([rng.uniform(-25, 25, (20, 2)), rng.uniform(0.5, 8, (20, 2)), rng.uniform(-4, 4, 20)])
    polys = [_star_polygon(rng, rng.uniform(-25, 25, 2)) for _ in range(12)]
    got_b, got_p = segments_hit_boxes(a, b, boxes), segments_hit_polygons(a, b, polys)
    lines = [LineString([p, q]) for p, q in zip(a, b)]
    want_b = np.array([[ln.intersects(_box_polygon(bx)) for bx in boxes] for ln in lines])
    want_p = np.array([[ln.intersects(Polygon(p)) for p in polys] for ln in lines])
    assert want_b.any() and not want_b.all() and want_p.any()
    np.testing.assert_array_equal(got_b, want_b)
    np.testing.assert_array_equal(got_p, want_p)


def _random_targets(rng, n) -> ObjectArray:
    return ObjectArray(
        ids=np.arange(n), cls=np.ones(n, dtype=np.int64), xy=rng.uniform(-30, 30, (n, 2)), z=np.zeros(n),
        lwh=np.column_stack([rng.uniform(1, 6, n), rng.uniform(0.5, 2.5, n), np.ones(n)]),
        yaw=rng.uniform(-np.pi, np.pi, n), vxy=np.zeros((n, 2)),
    )


def test_visible_fraction_matches_shapely_brute_force():
    rng = np.random.default_rng(3)
    for _ in range(4):
        targets = _random_targets(rng, 15)
        boxes = np.column_stack([rng.uniform(-25, 25, (5, 2)), rng.uniform(1, 8, (5, 2)), rng.uniform(-4, 4, 5)])
        polys = [_star_polygon(rng, rng.uniform(-25, 25, 2)) for _ in range(3)]
        origin = rng.uniform(-5, 5, 2)
        got = visible_fraction(origin, targets, boxes, polys, samples=9)
        shapes = [_box_polygon(bx) for bx in boxes] + [Polygon(p) for p in polys]
        own = [_box_polygon(np.r_[targets.xy[i], targets.lwh[i, :2], targets.yaw[i]]) for i in range(15)]
        pts = box_points(targets.xy, targets.lwh[:, :2], targets.yaw, samples=9)
        want = np.array([
            np.mean([not any(LineString([origin, p]).intersects(s) for s in shapes + own[:i] + own[i + 1:]) for p in pts[i]])
            for i in range(15)
        ])
        np.testing.assert_allclose(got, want)


# --- LiDAR ------------------------------------------------------------------------------

def test_lidar_range_limit_and_base_link_frame():
    near, far = _car("near", [[40.0, 10.0]], yaw_deg=0.0), _car("far", [[0.0, 120.0]], yaw_deg=0.0)
    data = _open_field([near, far])
    data["ego"] = _car("ego", [[100.0, 50.0]], yaw_deg=90.0)  # near: 72.1 m away; far: 122.1 m
    world = World(Scenario.model_validate(data))
    lidar = Lidar(world.scenario.lidar, np.random.default_rng(0))
    dets = lidar.detect(world, 0.0)
    assert len(dets) == 1 and (dets.ids == -1).all() and (dets.sources == 1).all()
    want = map_to_base_points(np.array([[40.0, 10.0]]), world.ego_at(0.0))[0]  # (-40, 60)
    np.testing.assert_allclose(dets.xy[0], want, atol=0.5)
    assert dets.yaw[0] == pytest.approx(-np.pi / 2, abs=0.15)
    np.testing.assert_allclose(dets.cov_xy[0], 0.01 * np.eye(2))


def _first_visible_distance(scenario: Scenario) -> float:
    world = World(scenario)
    lidar, k = Lidar(scenario.lidar, np.random.default_rng(0)), world.target_id - 1
    for t in frame_times(scenario.lidar.rate_hz, 15.0):
        dist, vis = lidar.visibility(world, t)
        if dist[k] <= scenario.lidar.range_m and vis[k] >= scenario.lidar.min_visible_fraction:
            ego, p = world.ego_at(t), world.actors_at(t).xy[k]
            return float(np.hypot(p[0] - ego.x, p[1] - ego.y))
    return float("nan")


def test_lidar_adversary_hidden_by_van_then_visible():
    data = _rlr_dict()
    data["lidar"]["detection_probability"] = 1.0
    sc = Scenario.model_validate(data)
    world, lidar = World(sc), Lidar(sc.lidar, np.random.default_rng(0))
    k = world.target_id - 1

    def sees_target(t):
        ego = world.ego_at(t)
        p = map_to_base_points(world.actors_at(t).xy[k : k + 1], ego)[0]
        d = lidar.detect(world, t)
        return bool(len(d)) and np.hypot(*(d.xy - p).T).min() < 1.0

    assert not any(sees_target(t) for t in np.arange(0.0, 9.85, 0.1))  # in range from t ~ 4 s
    assert all(sees_target(t) for t in np.arange(10.0, 11.0, 0.1))
    assert 15.0 <= _first_visible_distance(sc) <= 30.0
    data["actors"] = [a for a in data["actors"] if a["name"] != "van"]
    assert _first_visible_distance(Scenario.model_validate(data)) > 40.0  # the van is the occluder


# --- RSU camera -------------------------------------------------------------------------

def test_camera_range_fov_and_buildings():
    cars = [_car("in", [[50.0, 5.0]], yaw_deg=0.0), _car("too-far", [[90.0, 0.0]], yaw_deg=0.0),
            _car("off-axis", [[10.0, 30.0]], yaw_deg=0.0), _car("behind", [[-30.0, 0.0]], yaw_deg=0.0),
            _car("hidden", [[60.0, -30.0]], yaw_deg=0.0), _car("car-shadow", [[70.0, 5.5]], yaw_deg=0.0)]
    data = _open_field(cars, buildings=[{"box": {"x": 30.0, "y": -15.0, "l": 6.0, "w": 6.0}}])
    world = World(Scenario.model_validate(data))
    camera = RsuCamera(world.scenario.rsu, np.random.default_rng(0))
    for t in range(5):
        dets, delay = camera.detect(world, float(t))
        assert 0.08 <= delay <= 0.12
        assert (dets.ids == -1).all() and (dets.sources == 2).all() and not dets.vxy.any()
        # "in" and "car-shadow" (behind "in" as seen from the pole: cars do not occlude)
        np.testing.assert_allclose(np.sort(dets.xy[:, 0]), [50.0, 70.0], atol=6.0)


def test_camera_on_red_light_runner_sees_adversary_early():
    sc = load_scenario(RLR)
    world, camera = World(sc), RsuCamera(sc.rsu, np.random.default_rng(0))
    k = world.target_id - 1
    covered = [camera.coverage(world, t)[1][k] for t in np.arange(0.0, 12.0, 0.05)]
    first = np.arange(0.0, 12.0, 0.05)[np.argmax(covered)]
    ego, p = world.ego_at(first), world.actors_at(first).xy[k]
    assert 70.0 <= np.hypot(p[0] - ego.x, p[1] - ego.y) <= 95.0
    assert not camera.coverage(world, 12.0)[1][k]  # past the field of view


def test_camera_error_model_statistics():
    rng = np.random.default_rng(11)
    ang = rng.uniform(-0.7, 0.7, 60)
    rad = np.r_[rng.uniform(10, 48, 30), rng.uniform(52, 78, 30)]
    cars = [_car(f"c{i}", [[r * np.cos(a), r * np.sin(a)]], yaw_deg=0.0) for i, (r, a) in enumerate(zip(rad, ang))]
    world = World(Scenario.model_validate(_open_field(cars)))
    camera = RsuCamera(world.scenario.rsu, np.random.default_rng(0))
    truth = world.actors_at(0.0).xy
    errors = np.stack([camera.detect(world, 0.0)[0].xy - truth for _ in range(150)])  # all 60 seen
    euclid = np.hypot(errors[..., 0], errors[..., 1])
    assert euclid[:, :30].mean() == pytest.approx(0.8, rel=0.05)
    assert euclid[:, 30:].mean() == pytest.approx(1.7, rel=0.05)
    np.testing.assert_allclose(mean_error_at(np.array([0.0, 50.0, 50.1, 200.0]), world.scenario.rsu), [0.8, 0.8, 1.7, 1.7])
    lwh = camera.detect(world, 0.0)[0].lwh
    np.testing.assert_allclose(lwh.mean(axis=0), [4.6, 1.85, 1.5], atol=0.05)  # class prior, not truth


# --- determinism and timing -------------------------------------------------------------

def _run(seed: int, world: World) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    sc = world.scenario
    lidar, camera, loc = Lidar(sc.lidar, rng), RsuCamera(sc.rsu, rng), Localization(sc.localization, rng)
    out = []
    for t in np.arange(8.0, 12.0, 0.1):
        lid = lidar.detect(world, t)
        cam, delay = camera.detect(world, t)
        pose = loc.measure(world, t)
        out += [lid.xy, lid.vxy, lid.yaw, cam.xy, cam.lwh, np.array([delay, pose.x, pose.y, pose.yaw])]
    return out


def test_determinism_same_seed_same_output():
    world = World(load_scenario(RLR))
    a, b, c = _run(5, world), _run(5, world), _run(6, world)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not all(x.shape == y.shape and np.array_equal(x, y) for x, y in zip(a, c))


def test_frame_times():
    t = frame_times(10.0, 30.0)
    assert len(t) == 300 and t[0] == 0.0 and t[-1] == pytest.approx(29.9)
    t = frame_times(5.0, 1.0, phase_s=0.05)
    np.testing.assert_allclose(t, [0.05, 0.25, 0.45, 0.65, 0.85])


def test_localization_noise_is_small_unbiased_and_slowly_drifting():
    world = World(load_scenario(RLR))
    loc = Localization(world.scenario.localization, np.random.default_rng(2))
    # samples a few correlation times apart are nearly independent: stationary mean and std
    poses = np.array([[p.x, p.y, p.yaw] for p in (loc.measure(world, 1.0 + 20.0 * k) for k in range(2000))])
    np.testing.assert_allclose(poses.mean(axis=0), [5.25, -12.35, np.pi / 2], atol=0.01)
    np.testing.assert_allclose(poses.std(axis=0), [0.05, 0.05, 0.005], rtol=0.1)
    # 10 Hz samples drift: consecutive errors are strongly correlated (a = exp(-0.1 / 5) = 0.98)
    loc = Localization(world.scenario.localization, np.random.default_rng(3))
    x = np.array([loc.measure(world, 0.1 * k).x for k in range(5000)]) - 5.25
    assert np.corrcoef(x[:-1], x[1:])[0, 1] > 0.95


def _view_trajectories(world: World) -> Trajectories:
    """The trajectories of a view's own actors alone (what each view evaluated before the shared bodies)."""
    bodies = list(world.scenario.actors) + list(world.scenario.vehicles)
    return Trajectories([bodies[r].trajectory for r in world._rows])


def test_actors_on_their_own_clocks_equal_one_evaluation_per_spawn_time():
    """World.actors_at evaluates every actor at t - spawn_s at once: bit-equal to evaluating the
    trajectories once per distinct spawn time and keeping each actor's own rows."""
    world = World(load_scenario("two-rsu-corridor"))
    own = _view_trajectories(world)
    spawns = np.unique(world._spawn_s)
    assert len(spawns) > 1
    for t_s in np.linspace(0.0, world.duration_s, 37):
        want = [np.array(a) for a in own.at(t_s - spawns[0])]
        for spawn in spawns[1:]:
            rows = world._spawn_s == spawn
            for full, part in zip(want, own.at(t_s - spawn)):
                full[rows] = part[rows]
        got = world._bodies.at(t_s)
        for got_column, ref in zip(got, want):
            np.testing.assert_array_equal(got_column[world._rows], ref, strict=True)


@pytest.mark.parametrize("name", bundled_scenarios())
def test_views_sharing_the_bodies_equal_their_own_evaluation_bit_for_bit(name):
    """Every view of a scenario (each vehicle's, the site's) takes its actors' rows of one evaluation
    of all bodies (kept per instant): the bits of evaluating its own actors alone, at its own clocks
    (a scalar time when none spawns late, as before), whatever the order the views ask in."""
    scenario = load_scenario(name)
    views = [World(scenario, ego=v.name) for v in scenario.vehicles] + [World(scenario, site=True)]
    assert len({id(w._bodies) for w in views}) == 1
    times = np.r_[0.0, np.linspace(-0.5, scenario.duration_s + 5.0, 41)]
    for t_s in np.r_[times, times[::-1]]:
        for world in views[::-1] if t_s > 3.0 else views:
            own = _view_trajectories(world)
            want = own.at(t_s - world._spawn_s if world._timed else float(t_s))
            got = world.actors_at(float(t_s))
            present = world.present(t_s) if world._timed else slice(None)  # an untimed view keeps every actor
            for column, ref in zip(("xy", "yaw", "vxy", "axy"), want):
                assert getattr(got, column).tobytes() == ref[present].tobytes(), (name, column, t_s)


def _reference_state(traj, t_s):
    """Trajectories.at as written before the one-gather lookups (np.where over every branch)."""
    sp, pa = traj._speed, traj._paths
    k = np.maximum((sp._t <= t_s).sum(axis=1) - 1, 0)
    before, r = t_s < sp._t[:, 0], sp._rows

    def f_at(t):
        kk = np.maximum((sp._t <= t).sum(axis=1) - 1, 0)
        b = t < sp._t[:, 0]
        dt = np.where(b, 0.0, t - sp._t[r, kk])
        a = np.where(b, 0.0, sp._a[r, kk])
        return np.where(b, sp._v[:, 0] * (t - sp._t[:, 0]), sp._f[r, kk] + sp._v[r, kk] * dt + 0.5 * a * dt**2)

    dt = np.where(before, 0.0, t_s - sp._t[r, k])
    a = np.where(before, 0.0, sp._a[r, k])
    v, s = sp._v[r, k] + a * dt, f_at(t_s) - f_at(0.0)
    s_c = np.clip(s, 0.0, pa.length)
    j = np.minimum(np.maximum((pa._cum <= s_c[:, None]).sum(axis=1) - 1, 0), pa._last_seg)
    u = pa._u[r, j]
    xy = pa._p[r, j] + (s_c - pa._cum[r, j])[:, None] * u
    moving = (s >= 0.0) & (s < pa.length)
    return xy, np.arctan2(u[:, 1], u[:, 0]), np.where(moving, v, 0.0)[:, None] * u, np.where(moving, a, 0.0)[:, None] * u


@pytest.mark.parametrize("name", bundled_scenarios())
def test_trajectories_equal_the_per_branch_reference_bit_for_bit(name):
    world = World(load_scenario(name))
    for traj in (_view_trajectories(world), world._ego):
        for t_s in np.r_[-3.0, np.linspace(-0.5, world.duration_s + 5.0, 53)]:
            for got, want in zip(traj.at(t_s), _reference_state(traj, t_s)):
                np.testing.assert_array_equal(got, want, strict=True)


@pytest.mark.parametrize("name", bundled_scenarios())
def test_compiled_states_equal_the_numpy_evaluation_bit_for_bit(name):
    """Trajectories.at (compiled, body by body) gives the bits of at_numpy: one time for every body and
    one time per body (late spawns), before the first key and after the path's end, signed zeros too."""
    scenario = load_scenario(name)
    bodies = list(scenario.actors) + list(scenario.vehicles)
    traj = Trajectories([b.trajectory for b in bodies])
    rng = np.random.default_rng(9)
    times = np.r_[-3.0, -0.0, 0.0, np.linspace(-0.5, scenario.duration_s + 5.0, 61), scenario.duration_s + 60.0]
    per_body = [t - rng.choice([0.0, 0.0, 1.5, 7.25], len(bodies)) for t in times]
    for t_s in [*times.tolist(), *per_body]:
        for got, want in zip(traj.at(t_s), traj.at_numpy(t_s)):
            assert got.dtype == want.dtype and got.shape == want.shape and got.tobytes() == want.tobytes(), (name, t_s)


@pytest.mark.parametrize("name", bundled_scenarios())
def test_one_body_in_floats_equals_the_vectorised_rows_bit_for_bit(name):
    """Trajectories.body(i).at (plain floats, World.ego_at) gives the bits of Trajectories.at row i:
    every actor and the ego of every bundled scenario, before the first key and after the path's end
    included, signed zeros too (compared as raw float64 bytes)."""
    world = World(load_scenario(name))
    times = np.r_[-3.0, 0.0, np.linspace(-0.5, world.duration_s + 5.0, 97), world.duration_s + 60.0]
    for traj in (_view_trajectories(world), world._ego):
        bodies = [traj.body(i) for i in range(len(traj._paths.length))]
        for t_s in times:
            xy, yaw, vxy, _ = traj.at(t_s)
            want = np.column_stack([xy, yaw, vxy])  # (N, 5): x, y, yaw, vx, vy
            got = np.array([b.at(t_s) for b in bodies], dtype=np.float64)
            assert got.tobytes() == want.tobytes(), (name, t_s)
    pose = world.ego_at(7.3)
    xy, yaw, vxy, _ = world._ego.at(7.3)
    assert (pose.x, pose.y, pose.yaw, pose.vx, pose.vy) == (xy[0, 0], xy[0, 1], yaw[0], vxy[0, 0], vxy[0, 1])


@pytest.mark.parametrize("name", bundled_scenarios())
def test_visible_fraction_of_sampled_targets_equals_sampling_all(name):
    """visible_fraction(..., sampled=mask) gives the sampled targets the very fractions of the
    full test (each point is tested on its own; the unsampled targets still occlude) and 0 to the
    rest: from the ego with the actors occluding, and from each RSU pole without."""
    scenario = load_scenario(name)
    world, site = World(scenario), World(scenario, site=True)
    rng = np.random.default_rng(5)
    for t_s in np.linspace(0.0, world.duration_s, 23):
        ego = world.ego_at(t_s)
        views = [(np.array([ego.x, ego.y]), world.actors_at(t_s), True)]
        views += [(np.array([r.position.x, r.position.y]), site.actors_at(t_s), False) for r in scenario.rsus]
        for origin, gt, occlude in views:
            full = visible_fraction(origin, gt, world.building_boxes, world.building_polygons, targets_occlude=occlude)
            mask = rng.random(len(gt)) < 0.6
            part = visible_fraction(origin, gt, world.building_boxes, world.building_polygons, targets_occlude=occlude,
                                    sampled=mask)
            assert part[mask].tobytes() == full[mask].tobytes()
            assert not part[~mask].any()


@pytest.mark.parametrize("name", ["two-rsu-corridor", "dense-intersection"])
def test_actors_at_adds_the_kinematics_to_read_only_static_columns(name):
    """World.actors_at = the per-call construction it replaced (every column, bit for bit, spawned
    actors only), its time-independent columns shared read-only, its kinematics fresh per call."""
    world = World(load_scenario(name))
    for t_s in (0.0, 3.7, 11.2, world.duration_s - 0.1):
        got = world.actors_at(t_s)
        xy, yaw, vxy, axy = _view_trajectories(world).at(t_s - world._spawn_s if world._timed else t_s)
        n = len(world.ids)
        want = ObjectArray(ids=world.ids.copy(), cls=world.cls.copy(), xy=xy, z=world.lwh[:, 2] / 2.0,
                           lwh=world.lwh.copy(), yaw=yaw, vxy=vxy, axy=axy, cov_xy=np.zeros((n, 2, 2)),
                           confidence=np.ones(n), sources=np.zeros(n, dtype=np.int64)).take(world.present(t_s))
        for column in ("ids", "cls", "xy", "z", "lwh", "yaw", "vxy", "axy", "yaw_rate", "cov_xy", "confidence",
                       "cov_vxy", "age_s", "sources"):
            a, b = getattr(got, column), getattr(want, column)
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), column
    untimed = World(load_scenario("dense-intersection"))
    first, second = untimed.actors_at(1.0), untimed.actors_at(2.0)
    assert first.ids is second.ids and not first.ids.flags.writeable
    assert first.xy is not second.xy and first.xy.flags.writeable
    # every column of the shared static truth is read-only (v2i.core.objects.read_only), whichever ObjectArray has
    for world in (untimed, World(load_scenario("two-rsu-corridor"))):
        world.actors_at(3.7)
        for static in (world._static, *world._static_present.values()):
            assert not any(column.flags.writeable for column in static.__dict__.values())


def test_compiled_states_refuse_a_time_per_body_of_another_count():
    traj = Trajectories([a.trajectory for a in load_scenario(RLR).actors])
    n = len(traj._paths.length)
    assert len(traj.at(np.zeros(n))[1]) == len(traj.at(np.zeros(1))[1]) == n
    with pytest.raises(ValueError, match="one time, or one per body"):
        traj.at(np.zeros(n + 1))
