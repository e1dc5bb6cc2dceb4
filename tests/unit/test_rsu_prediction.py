"""rsu_service.prediction and v2i.runtime.site.lane_predictor: the lane predictor loaded once per map
file and shared."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from v2i.core.objects import ObjectArray
from rsu_service.prediction import make_predictor
from v2i.runtime.site import lane_predictor
from v2i.sim.maps import lane_predictor as fresh_lane_predictor, map_path
from v2i.sim.scenario_site import scenario_site


def test_the_predictor_of_a_map_is_loaded_once_and_predicts_as_a_fresh_one():
    site = scenario_site("dense-intersection")
    shared = lane_predictor(site)
    assert lane_predictor(scenario_site("dense-intersection")) is shared
    fresh = fresh_lane_predictor("dense-intersection")
    rng = np.random.default_rng(1)
    objs = ObjectArray(ids=np.arange(6), cls=np.ones(6, dtype=np.int64), xy=rng.uniform(-40, 40, (6, 2)),
                       z=np.zeros(6), lwh=np.tile([4.5, 1.8, 1.5], (6, 1)), yaw=rng.uniform(-3, 3, 6),
                       vxy=rng.normal(0, 8, (6, 2)))
    assert make_predictor("lane", site)(objs, 5.0, 0.1).tobytes() == \
        fresh.predict_trajectories(objs, 5.0, 0.1).tobytes()


def test_a_changed_map_file_is_loaded_again(tmp_path):
    """A scenario file with a map beside it: a new modification time or size gives a new predictor."""
    name = "red-light-runner"
    scenario = tmp_path / f"{name}.yaml"
    shutil.copy(scenario_path(name), scenario)
    osm = tmp_path / f"{name}.osm"
    shutil.copy(map_path(name), osm)
    first = lane_predictor(scenario_site(str(scenario)))
    assert lane_predictor(scenario_site(str(scenario))) is first
    stat = osm.stat()
    os.utime(osm, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    assert lane_predictor(scenario_site(str(scenario))) is not first


def test_no_map_is_an_error_and_auto_falls_back_to_constant_velocity(tmp_path):
    scenario = tmp_path / "custom.yaml"
    shutil.copy(scenario_path("red-light-runner"), scenario)
    site = scenario_site(str(scenario))
    assert site.map is None
    with pytest.raises(ValueError, match="Lanelet2 map"):
        lane_predictor(site)
    with pytest.raises(ValueError, match="Lanelet2 map"):
        make_predictor("lane", site)
    from v2i.fusion.motion import trajectories_cv

    assert make_predictor("auto", site) is trajectories_cv


def scenario_path(name: str):
    from importlib import resources

    return resources.files("v2i.sim") / "scenarios" / f"{name}.yaml"
