"""The RSU's long-horizon trajectory predictor: lane-following on the scenario's Lanelet2 map
(Saravanan et al.'s lanelet-based predictor) or constant velocity."""

from __future__ import annotations

from functools import lru_cache

from v2i.fusion.lane_prediction import LanePredictor  # (imported here: its compiled loops load with the service's kernels)
from v2i.fusion.motion import trajectories_cv
from v2i.sim.maps import lane_predictor, scenario_map

from rsu_service.config import PREDICTORS
from rsu_service.pipeline import TrajectoryPredictor


def make_predictor(kind: str, scenario: str) -> TrajectoryPredictor:
    """``lane`` (needs a map), ``cv``, or ``auto``: lane when the scenario has a map, else cv."""
    if kind not in PREDICTORS:
        raise ValueError(f"predictor must be one of {PREDICTORS}, got {kind!r}")
    if kind == "cv" or (kind == "auto" and scenario_map(scenario) is None):
        return trajectories_cv
    lanes = shared_lane_predictor(scenario)
    return lambda objs, horizon_s, step_s: lanes.predict_trajectories(objs, horizon_s, step_s)


def shared_lane_predictor(scenario: str) -> LanePredictor:
    """``v2i.sim.maps.lane_predictor(scenario)``, loaded once per map file (its path, modification time and
    size; ~26 ms a load): a LanePredictor is read-only once built, so the RSUs of a run, a restarted
    RSU and the runs of one process share it. No map: lane_predictor's error."""
    path = scenario_map(scenario)
    if path is None:
        return lane_predictor(scenario)
    stat = path.stat()
    return _loaded_lane_predictor(scenario, str(path), stat.st_mtime_ns, stat.st_size)


@lru_cache(maxsize=8)
def _loaded_lane_predictor(scenario: str, path: str, mtime_ns: int, size: int) -> LanePredictor:
    """The predictor of ``scenario``'s map at ``path`` as it was at (``mtime_ns``, ``size``)."""
    return lane_predictor(scenario)
