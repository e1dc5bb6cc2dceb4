"""Scoring of fused outputs against ground truth (pure; shared by ``eval`` and ``demo``)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fusion.association import assign, center_distance_cost
from fusion.frames import map_to_base
from fusion.geometry import bev_boxes, bev_iou_matrix
from fusion.objects import ObjectArray
from fusion.wire import objects_from_states
from schemas.messages import FusedObjectList, PredictionList

from obu_service.fusion_mode import MODES
from obu_service.planning import path_array

from .detection_metrics import center_distance_ap, mot_metrics, nees

MAX_RANGE_M = 80.0  # detection metrics cover actors within this distance of the ego
MATCH_GATE_M = 4.0  # an output object within 4 m of a true actor (nuScenes' widest threshold) is its detection


@dataclass(frozen=True)
class TargetScore:
    """How one actor appears in a stream of outputs: mean BEV IoU, RMSE and the NEES of the
    stated position covariance (``detection_metrics.nees``: mean, and the share inside the
    95 % chi-square interval) over the cycles where it is detected, and the ego-target
    distance at its first detection."""

    detected_cycles: int
    mean_bev_iou: float | None
    rmse_m: float | None
    first_detection_distance_m: float | None
    first_detection_time_s: float | None
    nees_mean: float | None = None
    nees_fraction_inside: float | None = None

    def as_dict(self) -> dict:
        return {
            "mean_bev_iou": _round(self.mean_bev_iou), "rmse_m": _round(self.rmse_m),
            "first_detection_distance_m": _round(self.first_detection_distance_m),
            "first_detection_time_s": _round(self.first_detection_time_s), "detected_cycles": self.detected_cycles,
            "nees_mean": _round(self.nees_mean), "nees_fraction_inside": _round(self.nees_fraction_inside),
        }


def _round(v: float | None, nd: int = 4) -> float | None:
    return None if v is None else round(float(v), nd)


def match_target(truth: ObjectArray, output: ObjectArray, target_id: int) -> int | None:
    """Index of the output object assigned to the target, by a global centre-distance
    assignment of all true actors to all output objects (so a neighbour cannot be
    mistaken for the target); None when the target is not detected."""
    if not len(output) or not len(truth):
        return None
    result = assign(center_distance_cost(truth.xy, output.xy), MATCH_GATE_M)
    rows = result.matches[truth.ids[result.matches[:, 0]] == target_id]
    return int(rows[0, 1]) if len(rows) else None


def score_target(world, outputs: Sequence[FusedObjectList], start_ns: int, sources_mask: int | None = None) -> TargetScore:
    """Score ``world.target_id`` in the outputs; with ``sources_mask`` only objects whose
    sources intersect it count (SOURCE_VEHICLE gives the vehicle-only view)."""
    ious, errors, covs, first = [], [], [], None
    for msg in sorted(outputs, key=lambda m: m.cycle_time_ns):
        t_s = (msg.cycle_time_ns - start_ns) * 1e-9
        ego = world.ego_at(t_s)
        truth = map_to_base(world.actors_at(t_s), ego)  # true base_link at the cycle time
        out = objects_from_states(msg.objects)
        if sources_mask is not None:
            out = out.take((out.sources & sources_mask) != 0)
        k = match_target(truth, out, world.target_id)
        if k is None:
            continue
        i = int(np.flatnonzero(truth.ids == world.target_id)[0])
        ious.append(bev_iou_matrix(bev_boxes(truth.take([i])), bev_boxes(out.take([k])))[0, 0])
        errors.append(out.xy[k] - truth.xy[i])
        covs.append(out.cov_xy[k])
        if first is None:
            first = (float(np.linalg.norm(truth.xy[i])), t_s)
    consistency = nees(np.array(errors), np.array(covs))
    return TargetScore(
        detected_cycles=len(ious),
        mean_bev_iou=float(np.mean(ious)) if ious else None,
        rmse_m=float(np.sqrt(np.mean(np.sum(np.square(errors), axis=1)))) if errors else None,
        first_detection_distance_m=first[0] if first else None,
        first_detection_time_s=first[1] if first else None,
        nees_mean=consistency["mean"], nees_fraction_inside=consistency["fraction_inside"],
    )


def deadline_miss_ratio(cycle_times_ns: Sequence[int], outputs: Sequence[FusedObjectList], deadline_ms: float) -> float:
    """Share of expected cycles with no output published by cycle time + deadline."""
    if not len(cycle_times_ns):
        return 0.0
    limit_ns = int(deadline_ms * 1e6)
    on_time = {m.cycle_time_ns for m in outputs if m.publish_time_ns <= m.cycle_time_ns + limit_ns}
    return sum(1 for t in cycle_times_ns if t not in on_time) / len(cycle_times_ns)


def mode_share(modes: Sequence[str]) -> dict[str, float]:
    """Share of cycles per fusion mode, keyed ``intra``, ``inter``, ``planning``, ``vehicle_only``."""
    return {m.replace("-", "_"): round(sum(x == m for x in modes) / max(len(modes), 1), 4) for m in MODES}


CLOCK_WARMUP_S = 5.0  # clock errors are scored after the estimator's first 5 s
STEP_SETTLE_S = 3.0  # ... and outside the 3 s after an injected RSU clock step
STEP_RECOVERED_MS = 1.0  # a step is recovered once the error stays below 1 ms


def _error_stats(err_ms: np.ndarray) -> dict:
    """p50 / p95 / max (None without samples) and the sample count."""
    if not len(err_ms):
        return {"p50": None, "p95": None, "max": None, "samples": 0}
    p50, p95 = np.percentile(err_ms, [50, 95])
    return {"p50": round(float(p50), 4), "p95": round(float(p95), 4), "max": round(float(err_ms.max()), 4),
            "samples": int(len(err_ms))}


def clock_errors(samples: Sequence[tuple[int, int, int, float]], truth, start_ns: int, step_ns: int | None) -> dict:
    """Offset errors |estimate - truth| (ms) of the filter and of the naive single exchange,
    drift error (ppm) and step recovery time, from (t_ns, theta_ns, naive theta_ns, drift ppm)
    samples scored against ``truth`` (a DriftingClock: offset_at(t), drift_ppm).

    Scored samples: t >= start + CLOCK_WARMUP_S and, with a step, not within STEP_SETTLE_S after it.
    """
    rows = np.array([(t, est, naive, drift) for t, est, naive, drift in samples], dtype=float).reshape(-1, 4)
    true_ns = np.array([truth.offset_at(int(t)) for t in rows[:, 0]], dtype=float)
    err_ms, naive_ms = np.abs(rows[:, 1] - true_ns) * 1e-6, np.abs(rows[:, 2] - true_ns) * 1e-6
    scored = rows[:, 0] >= start_ns + CLOCK_WARMUP_S * 1e9
    if step_ns is not None:
        scored &= ~((rows[:, 0] >= step_ns) & (rows[:, 0] < step_ns + STEP_SETTLE_S * 1e9))
    drift_err = np.abs(rows[scored, 3] - truth.drift_ppm)
    report = {
        "clock_offset_error_ms": _error_stats(err_ms[scored]),
        "clock_offset_error_naive_ms": _error_stats(naive_ms[scored]),
        "clock_drift_error_ppm": round(float(np.median(drift_err)), 3) if len(drift_err) else None,
    }
    if step_ns is not None:
        report["clock_step_recovery_s"] = _recovery_s(rows[:, 0], err_ms, step_ns)
    return report


def _recovery_s(t_ns: np.ndarray, err_ms: np.ndarray, step_ns: int) -> float | None:
    """Seconds from the step until the error is below STEP_RECOVERED_MS for good; None if never."""
    after = t_ns >= step_ns
    bad = np.flatnonzero(after & (err_ms >= STEP_RECOVERED_MS))
    if not after.any():
        return None
    if not len(bad):
        return 0.0
    if bad[-1] == len(t_ns) - 1:
        return None
    return round((t_ns[bad[-1] + 1] - step_ns) * 1e-9, 3)


def displacement_error_m(world, handed: Sequence[PredictionList], start_ns: int) -> float | None:
    """Seed 003 eq. 1: mean |predicted - true location| over the points of the predicted paths
    handed to the planner (each RSU list once), for objects matched to a true actor at t0
    (centre-distance assignment, gate MATCH_GATE_M); points after the scenario's end are
    not scored. None when no path was handed over."""
    errors = []
    seen = set()
    end_s = world.scenario.duration_s
    for pred in handed:
        key = (pred.header.rsu_id, pred.header.seq)
        if key in seen:
            continue
        seen.add(key)
        t0_s = (pred.header.valid_time_ns - start_ns) * 1e-9
        objs = objects_from_states(pred.objects)
        truth = world.actors_at(t0_s)
        if not len(objs) or not len(truth):
            continue
        matches = assign(center_distance_cost(objs.xy, truth.xy), MATCH_GATE_M).matches  # (M, 2) object, actor
        if not len(matches):
            continue
        paths = path_array(pred)[matches[:, 0]]  # (M, K + 1, 3)
        for j in range(1, paths.shape[1]):
            t_s = t0_s + j * pred.step_ns * 1e-9
            if t_s > end_s:
                break
            true_xy = world.actors_at(t_s).xy[matches[:, 1]]  # actor order is fixed by the world
            errors += np.linalg.norm(paths[:, j, :2] - true_xy, axis=1).tolist()
    return round(float(np.mean(errors)), 4) if errors else None


def cycle_frames(world, outputs: Sequence[FusedObjectList], start_ns: int, max_range_m: float = MAX_RANGE_M):
    """(truth, output) ObjectArray pairs per output, both in the true base_link of its cycle,
    restricted to ``max_range_m`` of the ego (the region the detection metrics cover)."""
    frames = []
    for msg in outputs:
        t_s = (msg.cycle_time_ns - start_ns) * 1e-9
        truth = map_to_base(world.actors_at(t_s), world.ego_at(t_s))
        out = objects_from_states(msg.objects)
        frames.append((truth.take(np.linalg.norm(truth.xy, axis=1) <= max_range_m),
                       out.take(np.linalg.norm(out.xy, axis=1) <= max_range_m)))
    return frames


def detection_scores(world, outputs: Sequence[FusedObjectList], start_ns: int) -> dict:
    """Centre-distance mAP (0-40 m, 40-80 m, overall = 0-80 m) and MOTA / IDF1 of all actors."""
    frames = cycle_frames(world, outputs, start_ns)
    ap = center_distance_ap(frames, range_bins_m=((0.0, 40.0), (40.0, MAX_RANGE_M), (0.0, np.inf)))
    mot = mot_metrics([(t.ids, t.xy, o.ids, o.xy) for t, o in frames])
    return {"detection": ap, "tracking": {k: mot[k] for k in ("mota", "idf1", "id_switches")}}
