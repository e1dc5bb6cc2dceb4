"""rsu_service.prediction: the lane predictor loaded once per map file and shared."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from v2i.core.objects import ObjectArray
from rsu_service.prediction import make_predictor, shared_lane_predictor
from v2i.sim.maps import lane_predictor, map_path


def test_the_predictor_of_a_map_is_loaded_once_and_predicts_as_a_fresh_one():
    shared = shared_lane_predictor("dense-intersection")
    assert shared_lane_predictor("dense-intersection") is shared
    fresh = lane_predictor("dense-intersection")
    rng = np.random.default_rng(1)
    objs = ObjectArray(ids=np.arange(6), cls=np.ones(6, dtype=np.int64), xy=rng.uniform(-40, 40, (6, 2)),
                       z=np.zeros(6), lwh=np.tile([4.5, 1.8, 1.5], (6, 1)), yaw=rng.uniform(-3, 3, 6),
                       vxy=rng.normal(0, 8, (6, 2)))
    assert make_predictor("lane", "dense-intersection")(objs, 5.0, 0.1).tobytes() == \
        fresh.predict_trajectories(objs, 5.0, 0.1).tobytes()


def test_a_changed_map_file_is_loaded_again(tmp_path):
    """A scenario file with a map beside it: a new modification time or size gives a new predictor."""
    name = "red-light-runner"
    scenario = tmp_path / f"{name}.yaml"
    osm = tmp_path / f"{name}.osm"
    shutil.copy(map_path(name), osm)
    first = shared_lane_predictor(str(scenario))
    assert shared_lane_predictor(str(scenario)) is first
    stat = osm.stat()
    os.utime(osm, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    assert shared_lane_predictor(str(scenario)) is not first


def test_no_map_is_lane_predictors_error(tmp_path):
    with pytest.raises(ValueError, match="Lanelet2 map"):
        shared_lane_predictor(str(tmp_path / "custom.yaml"))
