"""The bundled scenarios: they load, their worlds evaluate, and each keeps its promise."""

import numpy as np
import pytest
import shapely
from shapely.strtree import STRtree

from v2i.core.objects import ObjectArray
from v2i.sim.occlusion import box_points
from v2i.sim.scenario import bundled_scenarios, load_scenario
from v2i.sim.sensors import Lidar, RsuCamera
from v2i.sim.world import World

NEW = ("highway-merge", "dense-intersection", "two-rsu-corridor", "connected-intersection")
KMH = 1.0 / 3.6  # m/s per km/h


@pytest.fixture(scope="module")
def worlds() -> dict[str, World]:
    return {name: World(load_scenario(name)) for name in bundled_scenarios()}


def _times(world: World, step_s: float) -> np.ndarray:
    return np.arange(0.0, world.duration_s, step_s)


def _footprints(world: World, t_s: float) -> list:
    """Ground footprints (shapely polygons) of every actor and the ego at t_s."""
    gt, ego = world.actors_at(t_s), world.ego_at(t_s)
    xy = np.vstack([gt.xy, [[ego.x, ego.y]]])
    lw = np.vstack([gt.lwh[:, :2], world.ego_size[None, :2]])
    corners = box_points(xy, lw, np.append(gt.yaw, ego.yaw), samples=5)[:, 1:]
    return list(shapely.polygons(corners))


def test_new_scenarios_are_bundled():
    assert set(NEW) <= set(bundled_scenarios())


@pytest.mark.parametrize("name", bundled_scenarios())
def test_world_evaluates_at_several_times(worlds, name):
    world = worlds[name]
    assert world.actor_names[world.target_id] == world.scenario.target
    for t in np.linspace(0.0, world.duration_s, 7):
        gt = world.actors_at(t)
        n = int(world.present(t).sum())  # the other vehicles are actors too; spawned ones only when present
        assert isinstance(gt, ObjectArray) and len(gt) == n
        assert gt.xy.shape == (n, 2) and np.isfinite(gt.xy).all() and np.isfinite(gt.vxy).all()
        ego = world.ego_at(t)
        assert np.isfinite([ego.x, ego.y, ego.yaw, ego.vx, ego.vy]).all()


@pytest.mark.parametrize("name", NEW)
def test_no_two_bodies_overlap(worlds, name):
    world = worlds[name]
    for t in _times(world, 0.5):
        boxes = _footprints(world, t)
        pairs = STRtree(boxes).query(boxes, predicate="intersects")
        clashes = [(i, j) for i, j in pairs.T if i < j]
        assert not clashes, f"t = {t:.1f} s: bodies {clashes} overlap"


def test_dense_intersection_has_at_least_60_actors_moving(worlds):
    world = worlds["dense-intersection"]
    classes = {a.cls.name for a in world.scenario.actors}
    assert {"CAR", "BUS", "CYCLIST", "PEDESTRIAN"} <= classes
    for t in _times(world, 1.0):
        speed = np.hypot(*world.actors_at(t).vxy.T)
        assert (speed > 0.1).sum() >= 60, f"t = {t:.1f} s"


def test_highway_speeds_between_70_and_110_kmh(worlds):
    world = worlds["highway-merge"]
    for t in _times(world, 0.5):
        speeds = np.append(np.hypot(*world.actors_at(t).vxy.T), np.hypot(world.ego_at(t).vx, world.ego_at(t).vy))
        assert speeds.min() >= 70.0 * KMH - 1e-9 and speeds.max() <= 110.0 * KMH + 1e-9, f"t = {t:.1f} s"


@pytest.mark.parametrize(("name", "hidden_times"), [
    ("highway-merge", (9.0, 11.0, 13.0, 15.0)),
    ("dense-intersection", (12.0, 13.0, 14.0, 15.0)),
])
def test_target_hidden_from_the_lidar_in_range_but_seen_by_the_rsu(worlds, name, hidden_times):
    world = worlds[name]
    sc = world.scenario
    lidar, camera = Lidar(sc.lidar, np.random.default_rng(0)), RsuCamera(sc.rsu, np.random.default_rng(0))
    i = world.target_id - 1
    for t in hidden_times:
        dist, vis = lidar.visibility(world, t)
        _, observable = camera.coverage(world, t)
        assert dist[i] <= sc.lidar.range_m and vis[i] < sc.lidar.min_visible_fraction, f"t = {t} s"
        assert observable[i], f"t = {t} s"
