"""The scenario format of many RSUs and vehicles: lists, migration, views, lifetimes, paths, speeds."""

import math
import tempfile
from importlib.resources import files
from pathlib import Path

import numpy as np
import pytest
import yaml

from v2i.sim.paths import rounded_path, speed_keys_from_distance
from v2i.sim.scenario import Scenario, ScenarioError, load_scenario
from v2i.sim.world import World

RLR = "red-light-runner"


def _rlr() -> dict:
    return yaml.safe_load((files("v2i.sim") / "scenarios" / f"{RLR}.yaml").read_text())


def _as_lists(data: dict) -> dict:
    """The red-light-runner in the list layout: rsus, vehicles (ego with its sensors)."""
    data = dict(data)
    ego = {**data.pop("ego"), "lidar": data.pop("lidar"), "localization": data.pop("localization")}
    rsu = data.pop("rsu")
    return {**data, "rsus": [rsu], "vehicles": [ego]}


def _two_vehicles(**actor) -> Scenario:
    data = _as_lists(_rlr())
    second = {"name": "car-2", "class": "car", "size": [4.5, 1.8, 1.5],
              "trajectory": {"path": [[-5.25, 40.0], [-5.25, 12.0]], "speed": [[0.0, 5.0]]}}
    data["vehicles"].append(second)
    if actor:
        data["actors"].append(actor)
    return Scenario.model_validate(data)


# --- layout ---------------------------------------------------------------------------------

def test_older_single_layout_equals_the_list_layout():
    old, new = Scenario.model_validate(_rlr()), Scenario.model_validate(_as_lists(_rlr()))
    assert old == new == load_scenario(RLR)
    assert old.rsu is old.rsus[0] and old.ego is old.vehicles[0] and old.lidar is old.vehicles[0].lidar


@pytest.mark.parametrize(("edit", "message"), [
    (lambda d: d.update(rsus=[d["rsu"]]), "not both"),
    (lambda d: d.update(vehicles=[d["ego"]]), "not both"),
    (lambda d: d.update(target="ego"), "not an actor"),
])
def test_mixed_or_wrong_layouts_are_named(edit, message):
    data = _rlr()
    edit(data)
    with pytest.raises(ValueError, match=message):
        Scenario.model_validate(data)


def test_sensors_without_their_vehicle_are_refused():
    data = _as_lists(_rlr())
    data["lidar"] = {"range_m": 50.0}
    with pytest.raises(ValueError, match="belong to a vehicle"):
        Scenario.model_validate(data)


def test_duplicate_rsu_ids_and_vehicle_lifetimes_are_refused():
    data = _as_lists(_rlr())
    data["rsus"].append(dict(data["rsus"][0]))
    with pytest.raises(ValueError, match="RSU ids must be unique"):
        Scenario.model_validate(data)
    data = _as_lists(_rlr())
    data["vehicles"][0]["spawn_s"] = 2.0
    with pytest.raises(ValueError, match="whole run"):
        Scenario.model_validate(data)


def test_rsu_index_names_the_rsus_of_a_multi_rsu_site():
    sc = load_scenario(RLR)
    assert sc.rsu_index("any-name") == 0  # a single-RSU scenario serves any service id
    data = _as_lists(_rlr())
    data["rsus"].append({**data["rsus"][0], "id": "rsu-2"})
    two = Scenario.model_validate(data)
    assert two.rsu_index("rsu-2") == 1 and two.rsu_by_id("rsu-2").id == "rsu-2"
    with pytest.raises(ScenarioError, match="rsu-nw"):
        two.rsu_index("rsu-9")


# --- views --------------------------------------------------------------------------------

def test_each_vehicle_sees_the_others_as_actors_with_stable_ids():
    sc = _two_vehicles()
    n = len(sc.actors)
    first, second, site = World(sc), World(sc, ego="car-2"), World(sc, site=True)
    assert first.vehicle_ids == {"ego": n + 1, "car-2": n + 2}
    assert list(first.actors_at(0.0).ids) == list(range(1, n + 1)) + [n + 2]
    assert list(second.actors_at(0.0).ids) == list(range(1, n + 2))
    assert list(site.actors_at(0.0).ids) == list(range(1, n + 3))
    # the same body in two views is at the same place
    ego = first.ego_at(3.0)
    assert np.allclose(second.positions_of(np.array([n + 1]), 3.0), [[ego.x, ego.y]])
    assert np.allclose(first.positions_of(np.array([0, n + 2]), 3.0)[1], second.positions_of(np.array([0]), 3.0)[0])
    with pytest.raises(ValueError, match="no ego"):
        site.ego_at(0.0)
    with pytest.raises(ScenarioError, match="car-2"):
        World(sc, ego="nobody")


def test_actors_exist_between_spawn_and_despawn_on_their_own_clock():
    sc = _two_vehicles(name="late-bike", **{"class": "cyclist"}, size=[1.8, 0.6, 1.7], spawn_s=5.0, despawn_s=9.0,
                       trajectory={"path": [[-60.0, -6.6], [60.0, -6.6]], "speed": [[0.0, 4.0]]})
    world = World(sc)
    bike = max(i for i, name in world.actor_names.items() if name == "late-bike")
    assert bike not in world.actors_at(4.99).ids and bike not in world.actors_at(9.0).ids
    at = world.actors_at(7.0)
    row = list(at.ids).index(bike)
    # its clock starts at spawn: 2 s at 4 m/s along +x
    assert at.xy[row] == pytest.approx([-52.0, -6.6]) and at.vxy[row] == pytest.approx([4.0, 0.0])
    assert len(world.actors_at(7.0)) == len(world.actors_at(0.0)) + 1


# --- paths and speeds ---------------------------------------------------------------------

def test_rounded_corner_is_a_tangent_arc_of_the_radius():
    radius = 8.0
    pts = np.array(rounded_path([(0.0, -50.0), (0.0, 0.0), (50.0, 0.0)], radius))  # right turn at the origin
    assert tuple(pts[0]) == (0.0, -50.0) and tuple(pts[-1]) == (50.0, 0.0)
    arc = pts[1:-1]
    assert np.allclose(np.hypot(arc[:, 0] - radius, arc[:, 1] + radius), radius)  # centre (8, -8)
    assert tuple(arc[0]) == pytest.approx((0.0, -radius)) and tuple(arc[-1]) == pytest.approx((radius, 0.0))
    heading = np.degrees(np.arctan2(*np.diff(pts, axis=0).T[::-1]))
    assert np.abs(np.diff(heading)).max() <= 5.0 + 1e-9  # no kink larger than one arc step
    assert heading[0] == pytest.approx(90.0) and heading[-1] == pytest.approx(0.0)


def test_a_radius_that_does_not_fit_is_refused_with_the_segment():
    with pytest.raises(ValueError, match="does not fit"):
        rounded_path([(0.0, 0.0), (0.0, 5.0), (5.0, 5.0), (5.0, 0.0)], 4.0)  # two 90 deg corners 5 m apart need 8 m
    data = _rlr()
    data["actors"][0]["trajectory"] = {"path": [[0.0, 0.0], [0.0, 3.0], [50.0, 3.0]], "corner_radius_m": 10.0}
    with pytest.raises(ScenarioError, match="corner_radius_m"):
        _load(data)


def _load(data: dict) -> Scenario:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "s.yaml"
        path.write_text(yaml.safe_dump(data))
        return load_scenario(path)


def test_speed_by_distance_reaches_each_key_at_its_speed():
    keys = [(0.0, 10.0), (30.0, 10.0), (60.0, 0.0)]  # cruise 30 m, then brake to a stop in 30 m
    t_keys = speed_keys_from_distance(keys)
    assert t_keys == [(0.0, 10.0), (3.0, 10.0), (9.0, 0.0)]  # 2 * 30 m / (10 + 0) m/s = 6 s
    data = _rlr()
    data["actors"][0]["trajectory"] = {"path": [[-100.0, -1.75], [100.0, -1.75]], "speed_at_m": [list(k) for k in keys]}
    world = World(_load(data))
    for (s_m, v), (t_s, _) in zip(keys, t_keys):
        state = world.actors_at(t_s)
        assert state.xy[0, 0] == pytest.approx(-100.0 + s_m) and math.hypot(*state.vxy[0]) == pytest.approx(v)
    assert world.actors_at(20.0).xy[0, 0] == pytest.approx(-40.0)  # stopped at s = 60 m


@pytest.mark.parametrize(("keys", "message"), [
    ([(0.0, 0.0), (10.0, 0.0)], "never gets between"),
    ([(5.0, 0.0), (10.0, 3.0)], "could never reach"),
    ([(0.0, 3.0), (0.0, 4.0)], "strictly increase"),
])
def test_impossible_distance_profiles_are_refused(keys, message):
    with pytest.raises(ValueError, match=message):
        speed_keys_from_distance(keys)


def test_speed_by_time_and_by_distance_together_are_refused():
    data = _rlr()
    data["actors"][0]["trajectory"]["speed_at_m"] = [[0.0, 5.0]]
    with pytest.raises(ScenarioError, match="not both"):
        _load(data)
