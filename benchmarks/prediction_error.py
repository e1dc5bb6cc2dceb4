"""Prediction error on scenario ground truth: lane-following (Lanelet2 map) vs CV vs CA.

For each bundled scenario, every start time t0 = 0, dt0, ... <= duration - 5 s and every actor
moving at t0 (speed > 0.5 m/s): predict from the true state at t0 and compare with the true
positions at t0 + 0.1 .. 5 s (World(load_scenario(name))). Displacement error e_k = |p_k - p_true,k|;
ADE(h) = mean of e_k over t_k <= h, FDE(h) = e at t = h; averaged over (actor, t0) samples.

Methods: cv (x + v t), ca (x + v t + a t^2 / 2, as v2i.fusion.motion.predict_ca: reverses after a
stop), map (v2i.fusion.lane_prediction, most probable lane sequence, constant speed along the lane),
map-ca (the same with constant acceleration along the lane, stopping instead of reversing), and
map-ca-min2: the better of the two most probable lane sequences per sample (minADE_2 / minFDE_2,
an oracle pick, showing what the multi-hypothesis output ``predict_hypotheses`` covers).
Subsets: all moving actors; road users (pedestrians excluded: the map predictor gives them CV);
road users turning within the horizon (true heading changes by > 20 deg by then: includes
vehicles still approaching their turn); road users in a turn at t0 (heading changes by > 5 deg
in the next 0.5 s). Red-light-runner has only straight paths (no turning samples); highway-merge's
ramp and merge bend by < 20 deg. Also times one predictor call on ~100 objects.

    python benchmarks/prediction_error.py [--t0-step-s 0.1] [--scenario NAME ...] [--json]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from v2i.core.frames import wrap_angle
from v2i.fusion.lane_prediction import LanePredictionConfig, LanePredictor
from schemas.classes import ObjectClass
from v2i.sim.maps import MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG, map_path
from v2i.sim.scenario import bundled_scenarios, load_scenario
from v2i.sim.world import World

HORIZONS_S = (0.5, 1.0, 2.0, 3.0, 5.0)
STEP_S = 0.1
MAX_H_S = max(HORIZONS_S)
MOVING_MPS = 0.5
TURN_RAD = np.deg2rad(20.0)
IN_TURN_RAD, IN_TURN_S = np.deg2rad(5.0), 0.5
METHODS = ("cv", "ca", "map", "map-ca", "map-ca-min2")
SUBSETS = ("all moving", "road users", "turning within horizon", "in a turn at t0")


def predictors(name: str) -> dict[str, LanePredictor]:
    path = map_path(name)
    return {
        "map": LanePredictor.from_osm(path, MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG),
        "map-ca": LanePredictor.from_osm(path, MAP_ORIGIN_LAT_DEG, MAP_ORIGIN_LON_DEG,
                                         LanePredictionConfig(use_acceleration=True)),
    }


def predicted_xy(objs, times: np.ndarray, preds: dict[str, LanePredictor]) -> dict[str, np.ndarray]:
    """Per method, positions (N, H, T, 2) m at ``times`` (T,) s after the objects' time (H = 1
    but for the multi-hypothesis method)."""
    t = times[None, :, None]
    out = {
        "cv": objs.xy[:, None] + objs.vxy[:, None] * t,  # p + v t
        "ca": objs.xy[:, None] + objs.vxy[:, None] * t + 0.5 * objs.axy[:, None] * t**2,  # + a t^2 / 2
    }
    for key, pred in preds.items():
        out[key] = pred.predict_trajectories(objs, MAX_H_S, STEP_S)[..., :2]
    out = {k: v[:, None] for k, v in out.items()}
    hyp = preds["map-ca"].predict_hypotheses(objs, MAX_H_S, STEP_S)[0][:, :2, :, :2]
    out["map-ca-min2"] = np.concatenate([hyp, hyp[:, :1]], axis=1)[:, :2]  # a map without branches has H = 1
    return out


def scenario_samples(name: str, t0_step_s: float) -> dict:
    """Errors (samples, T) per method plus per-sample masks: road user, turning by step."""
    world = World(load_scenario(name))
    preds = predictors(name)
    times = STEP_S * np.arange(1, round(MAX_H_S / STEP_S) + 1)
    errors = {m: [] for m in METHODS}
    road, turned, in_turn = [], [], []
    for t0 in np.arange(0.0, world.duration_s - MAX_H_S + 1e-9, t0_step_s):
        objs = world.actors_at(t0)
        moving = np.hypot(objs.vxy[:, 0], objs.vxy[:, 1]) > MOVING_MPS
        if not moving.any():
            continue
        objs = objs.take(moving)
        truth = [world.actors_at(t0 + t).take(moving) for t in times]
        true_xy = np.stack([o.xy for o in truth], axis=1)  # (N, T, 2)
        dyaw = np.abs(wrap_angle(np.stack([o.yaw for o in truth], axis=1) - objs.yaw[:, None]))
        turned.append(np.maximum.accumulate(dyaw, axis=1) > TURN_RAD)  # turned by step k
        in_turn.append(dyaw[:, round(IN_TURN_S / STEP_S) - 1] > IN_TURN_RAD)
        road.append(objs.cls != int(ObjectClass.PEDESTRIAN))
        for m, xy in predicted_xy(objs, times, preds).items():
            errors[m].append(np.linalg.norm(xy - true_xy[:, None], axis=-1))  # (N, H, T)
    return {"errors": {m: np.concatenate(e) for m, e in errors.items()}, "road": np.concatenate(road),
            "turned": np.vstack(turned), "in_turn": np.concatenate(in_turn)}


def table(samples: dict) -> dict:
    """{subset: {method: {h: (ade, fde, n)}}}."""
    out = {}
    for subset in SUBSETS:
        out[subset] = {}
        for m in METHODS:
            e = samples["errors"][m]  # (samples, H, T)
            rows = {}
            for h in HORIZONS_S:
                k = round(h / STEP_S)
                mask = np.ones(len(e), bool) if subset == "all moving" else samples["road"].copy()
                if subset.startswith("turning"):
                    mask &= samples["turned"][:, k - 1]
                if subset.startswith("in a turn"):
                    mask &= samples["in_turn"]
                sel = e[mask, :, :k]  # min over hypotheses of ADE and of FDE (minADE_H, minFDE_H)
                rows[h] = (float(sel.mean(axis=2).min(axis=1).mean()) if len(sel) else np.nan,
                           float(sel[:, :, -1].min(axis=1).mean()) if len(sel) else np.nan, int(mask.sum()))
            out[subset][m] = rows
    return out


def merge(parts: list[dict]) -> dict:
    return {"errors": {m: np.concatenate([p["errors"][m] for p in parts]) for m in METHODS},
            "road": np.concatenate([p["road"] for p in parts]),
            "turned": np.vstack([p["turned"] for p in parts]),
            "in_turn": np.concatenate([p["in_turn"] for p in parts])}


def print_table(title: str, tab: dict) -> None:
    print(f"\n### {title}\n")
    print("| subset | method | " + " | ".join(f"{h:g} s ADE / FDE (m)" for h in HORIZONS_S) + " |")
    print("|---|---|" + "---|" * len(HORIZONS_S))
    for subset, methods in tab.items():
        if not any(methods["cv"][h][2] for h in HORIZONS_S):
            print(f"| {subset} (no samples) | | " + " | ".join("-" for _ in HORIZONS_S) + " |")
            continue
        ns = "/".join(str(methods["cv"][h][2]) for h in HORIZONS_S)
        for m, rows in methods.items():
            cells = " | ".join(f"{rows[h][0]:.2f} / {rows[h][1]:.2f}" for h in HORIZONS_S)
            print(f"| {subset} (n={ns}) | {m} | {cells} |" if m == "cv" else f"| | {m} | {cells} |")


def timing(n_calls: int = 200) -> dict:
    """Mean ms per call on the dense intersection at t = 12 s (91 actors) plus 9 copies moved 1 m."""
    world = World(load_scenario("dense-intersection"))
    objs = world.actors_at(12.0)
    objs = type(objs).concat([objs, objs.take(np.arange(9)).with_(xy=objs.xy[:9] + 1.0)])
    pred = predictors("dense-intersection")["map"]
    out = {"n_objects": len(objs)}
    for label, call in (("predict_objects(dt=0.3 s)", lambda: pred.predict_objects(objs, 0.3)),
                        ("predict_trajectories(5 s, 0.1 s)", lambda: pred.predict_trajectories(objs)),
                        ("predict_hypotheses(5 s, 0.1 s)", lambda: pred.predict_hypotheses(objs))):
        call()
        t = time.perf_counter()
        for _ in range(n_calls):
            call()
        out[label] = (time.perf_counter() - t) / n_calls * 1e3
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t0-step-s", type=float, default=0.1)
    ap.add_argument("--scenario", nargs="*", default=bundled_scenarios())
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    parts = {name: scenario_samples(name, args.t0_step_s) for name in args.scenario}
    tables = {name: table(s) for name, s in parts.items()}
    tables["all scenarios"] = table(merge(list(parts.values())))
    times = timing()
    if args.json:
        print(json.dumps({"tables": {k: {s: {m: {str(h): v for h, v in r.items()} for m, r in ms.items()}
                                         for s, ms in t.items()} for k, t in tables.items()},
                          "timing_ms": times}, indent=1))
        return
    for name, tab in tables.items():
        print_table(name, tab)
    print(f"\nper call, {times.pop('n_objects')} objects: " + ", ".join(f"{k} {v:.2f} ms" for k, v in times.items()))


if __name__ == "__main__":
    main()
