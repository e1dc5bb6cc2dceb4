"""The RSU's long-horizon trajectory predictor: lane-following on the scenario's Lanelet2 map
(seed 000's lanelet-based predictor) or constant velocity."""

from __future__ import annotations

from pathlib import Path

from fusion.lane_prediction import LanePredictor
from fusion.motion import trajectories_cv
from sim.maps import MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG, bundled_maps, map_path

from .pipeline import TrajectoryPredictor

PREDICTORS = ("auto", "lane", "cv")


def scenario_map(scenario: str) -> Path | None:
    """The Lanelet2 map of a scenario: the bundled one for a bundled name, else ``<file>.osm``
    next to a scenario YAML file; None when there is none."""
    if scenario in bundled_maps():
        return map_path(scenario)
    beside = Path(scenario).with_suffix(".osm")
    return beside if beside.is_file() else None


def make_predictor(kind: str, scenario: str) -> TrajectoryPredictor:
    """``lane`` (needs a map), ``cv``, or ``auto``: lane when the scenario has a map, else cv."""
    if kind not in PREDICTORS:
        raise ValueError(f"predictor must be one of {PREDICTORS}, got {kind!r}")
    path = None if kind == "cv" else scenario_map(scenario)
    if path is None:
        if kind == "lane":
            raise ValueError(f"predictor 'lane' needs a Lanelet2 map: none bundled for {scenario!r} "
                             f"and no {Path(scenario).with_suffix('.osm')} beside it")
        return trajectories_cv
    lanes = LanePredictor.from_osm(path, MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG)
    return lambda objs, horizon_s, step_s: lanes.predict_trajectories(objs, horizon_s, step_s)
