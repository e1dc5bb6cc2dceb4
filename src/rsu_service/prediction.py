"""The RSU's long-horizon trajectory predictor: lane-following on the scenario's Lanelet2 map
(seed 000's lanelet-based predictor) or constant velocity."""

from __future__ import annotations

import fusion.lane_prediction  # noqa: F401 (its compiled match loads with the service's kernels: fusion.jit.load_kernels)
from fusion.motion import trajectories_cv
from sim.maps import lane_predictor, scenario_map

from .config import PREDICTORS
from .pipeline import TrajectoryPredictor


def make_predictor(kind: str, scenario: str) -> TrajectoryPredictor:
    """``lane`` (needs a map), ``cv``, or ``auto``: lane when the scenario has a map, else cv."""
    if kind not in PREDICTORS:
        raise ValueError(f"predictor must be one of {PREDICTORS}, got {kind!r}")
    if kind == "cv" or (kind == "auto" and scenario_map(scenario) is None):
        return trajectories_cv
    lanes = lane_predictor(scenario)
    return lambda objs, horizon_s, step_s: lanes.predict_trajectories(objs, horizon_s, step_s)
