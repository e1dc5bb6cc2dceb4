"""The RSU's long-horizon trajectory predictor: lane-following on the site's Lanelet2 map
(Saravanan et al.'s lanelet-based predictor) or constant velocity."""

from __future__ import annotations

# (imported here: its compiled loops load with the service's kernels)
from v2i.fusion.lane_prediction import LanePredictor  # noqa: F401
from v2i.fusion.motion import trajectories_cv
from v2i.runtime.site import Site, lane_predictor

from rsu_service.config import PREDICTORS
from rsu_service.pipeline import TrajectoryPredictor


def make_predictor(kind: str, site: Site) -> TrajectoryPredictor:
    """``lane`` (needs a map), ``cv``, or ``auto``: lane when the site has a map, else cv. The lane
    predictor is the site map's shared one (``v2i.runtime.site.lane_predictor``)."""
    if kind not in PREDICTORS:
        raise ValueError(f"predictor must be one of {PREDICTORS}, got {kind!r}")
    if kind == "cv" or (kind == "auto" and site.map is None):
        return trajectories_cv
    lanes = lane_predictor(site)
    return lambda objs, horizon_s, step_s: lanes.predict_trajectories(objs, horizon_s, step_s)
