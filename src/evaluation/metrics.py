"""Scoring of fused outputs against ground truth (pure; shared by ``eval`` and ``demo``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from fusion.association import assign, center_distance_cost
from fusion.frames import map_to_base
from fusion.geometry import bev_boxes, bev_iou_matrix
from fusion.objects import ObjectArray
from fusion.wire import objects_from_states
from schemas.messages import FusedObjectList

from .detection_metrics import center_distance_ap, mot_metrics

MAX_RANGE_M = 80.0  # detection metrics cover actors within this distance of the ego
MATCH_GATE_M = 4.0  # an output object within 4 m of a true actor (nuScenes' widest threshold) is its detection


@dataclass(frozen=True)
class TargetScore:
    """How one actor appears in a stream of outputs: mean BEV IoU and RMSE over the
    cycles where it is detected, and the ego-target distance at its first detection."""

    detected_cycles: int
    mean_bev_iou: float | None
    rmse_m: float | None
    first_detection_distance_m: float | None
    first_detection_time_s: float | None

    def as_dict(self) -> dict:
        return {
            "mean_bev_iou": _round(self.mean_bev_iou), "rmse_m": _round(self.rmse_m),
            "first_detection_distance_m": _round(self.first_detection_distance_m),
            "first_detection_time_s": _round(self.first_detection_time_s), "detected_cycles": self.detected_cycles,
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
    ious, sq_errors, first = [], [], None
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
        sq_errors.append(float(np.sum((truth.xy[i] - out.xy[k]) ** 2)))
        if first is None:
            first = (float(np.linalg.norm(truth.xy[i])), t_s)
    return TargetScore(
        detected_cycles=len(ious),
        mean_bev_iou=float(np.mean(ious)) if ious else None,
        rmse_m=float(np.sqrt(np.mean(sq_errors))) if sq_errors else None,
        first_detection_distance_m=first[0] if first else None,
        first_detection_time_s=first[1] if first else None,
    )


def deadline_miss_ratio(cycle_times_ns: Sequence[int], outputs: Sequence[FusedObjectList], deadline_ms: float) -> float:
    """Share of expected cycles with no output published by cycle time + deadline."""
    if not len(cycle_times_ns):
        return 0.0
    limit_ns = int(deadline_ms * 1e6)
    on_time = {m.cycle_time_ns for m in outputs if m.publish_time_ns <= m.cycle_time_ns + limit_ns}
    return sum(1 for t in cycle_times_ns if t not in on_time) / len(cycle_times_ns)


def offset_error_ms(samples: Sequence[tuple[int, int]], true_offset_ns: Callable[[int], int]) -> dict:
    """p50 / p95 / max of |estimated - true| clock offset (ms) over (t_ns, estimate_ns) samples."""
    if not samples:
        return {"p50": None, "p95": None, "max": None, "samples": 0}
    err = np.array([abs(est - true_offset_ns(t)) for t, est in samples]) * 1e-6
    return {
        "p50": round(float(np.percentile(err, 50)), 4), "p95": round(float(np.percentile(err, 95)), 4),
        "max": round(float(err.max()), 4), "samples": len(samples),
    }


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
