"""Detection, tracking and consistency metrics (pure: numpy, scipy, motmetrics).

- ``center_distance_ap``: nuScenes-style average precision with a centre-distance match
  criterion, as OTVIC (seed 002 Sec. V-B) reports it: thresholds {0.5, 1, 2, 4} m, range bins
  0-40 m / 40-80 m / overall.
- ``mot_metrics``: CLEAR-MOT (MOTA) and identity (IDF1) metrics through ``motmetrics``.
- ``nees``: normalised estimation error squared of a filter's position estimates, against
  the chi-square(2) distribution its covariance claims.

All positions are bird's-eye-view centres in one frame (base_link: ego at the origin), metres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.spatial.distance import cdist
from scipy.stats import chi2

from fusion.objects import ObjectArray

# nuScenes' detection-eval constants (nuscenes-devkit, eval/detection/algo.py, configs/detection_cvpr_2019.json)
RECALL_SAMPLES = 101  # precision re-sampled at recall 0.00, 0.01, ..., 1.00
MIN_RECALL = 0.1
MIN_PRECISION = 0.1
DEFAULT_THRESHOLDS_M = (0.5, 1.0, 2.0, 4.0)
DEFAULT_RANGE_BINS_M = ((0.0, 40.0), (40.0, 80.0), (0.0, math.inf))

Frame = tuple[ObjectArray, ObjectArray]  # (truth, predictions), same frame and time


# --- centre-distance AP -------------------------------------------------------------------

def bin_label(lo: float, hi: float) -> str:
    """"overall" for [0, inf), else e.g. "0-40m"."""
    return "overall" if lo <= 0.0 and math.isinf(hi) else f"{lo:g}-{hi:g}m"


def _in_range(xy: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(N,) bool: lo <= ||xy|| < hi, distance to the ego at the origin (m)."""
    d = np.hypot(xy[:, 0], xy[:, 1]) if len(xy) else np.zeros(0)
    return (d >= lo) & (d < hi)


def _confidence_order(confidence: np.ndarray) -> np.ndarray:
    """Indices by descending confidence; ties: the later prediction first (the devkit's
    ``sorted((v, i) for ...)[::-1]``), so results match nuScenes exactly."""
    idx = np.arange(len(confidence))
    return np.lexsort((-idx, -np.asarray(confidence, dtype=float)))


def _greedy_match(dist: np.ndarray, rank: np.ndarray, threshold_m: float) -> np.ndarray:
    """nuScenes greedy matching in one frame: (P,) bool true positives.

    dist (P, G) centre distances (m); rank (P,) global confidence rank (0 = most confident).
    In rank order each prediction takes its nearest not-yet-taken truth (first index on a
    tie) and is a true positive iff that distance < threshold_m; otherwise a false positive.
    """
    n_pred, n_truth = dist.shape
    tp = np.zeros(n_pred, dtype=bool)
    if n_truth == 0:
        return tp
    taken = np.zeros(n_truth, dtype=bool)
    for p in np.argsort(rank, kind="stable"):
        row = np.where(taken, np.inf, dist[p])
        g = int(np.argmin(row))
        if row[g] < threshold_m:
            taken[g] = tp[p] = True
    return tp


def average_precision(confidence: np.ndarray, true_positive: np.ndarray, num_truth: int,
                      min_recall: float = MIN_RECALL, min_precision: float = MIN_PRECISION) -> float:
    """nuScenes AP from per-prediction confidences (P,) and true-positive flags (P,).

    In descending confidence: precision p_i = TP_i / (TP_i + FP_i), recall r_i = TP_i / num_truth
    (cumulative counts). p is re-sampled on the recall grid r = 0, 0.01, ..., 1 by linear
    interpolation through the points (r_i, p_i) (constant p_0 before r_0, 0 beyond the highest
    recall reached), then
        AP = mean_{r > min_recall} max(p(r) - min_precision, 0) / (1 - min_precision)
    i.e. the normalised area under the curve left after cutting the operating points with
    recall or precision below 10 %. AP = 0 with no truth or no true positive.
    """
    if num_truth == 0 or not np.any(true_positive):
        return 0.0
    order = _confidence_order(confidence)
    tp = np.cumsum(true_positive[order]).astype(float)
    fp = np.cumsum(~true_positive[order]).astype(float)
    recall_grid = np.linspace(0.0, 1.0, RECALL_SAMPLES)
    precision = np.interp(recall_grid, tp / num_truth, tp / (tp + fp), right=0.0)
    # + 1: the bin at exactly min_recall is excluded, as in the devkit's calc_ap
    clipped = np.maximum(precision[round(100 * min_recall) + 1:] - min_precision, 0.0)
    return min(float(np.mean(clipped)) / (1.0 - min_precision), 1.0)  # min: float round-off only


def _bin_frames(frames: Sequence[Frame], lo: float, hi: float) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per frame: truth xy (G, 2), prediction xy (P, 2) and confidence (P,) inside [lo, hi) m."""
    out = []
    for truth, pred in frames:
        keep_t, keep_p = _in_range(truth.xy, lo, hi), _in_range(pred.xy, lo, hi)
        out.append((truth.xy[keep_t], pred.xy[keep_p], pred.confidence[keep_p]))
    return out


def _bin_ap(binned: list[tuple[np.ndarray, np.ndarray, np.ndarray]], thresholds_m: Sequence[float]) -> dict:
    """AP per threshold and their mean over the frames of one range bin."""
    confidence = np.concatenate([c for _, _, c in binned]) if binned else np.zeros(0)
    rank = np.empty(len(confidence), dtype=np.int64)
    rank[_confidence_order(confidence)] = np.arange(len(confidence))
    starts = np.cumsum([0] + [len(c) for _, _, c in binned])
    dists = [cdist(p, t) if len(p) and len(t) else np.zeros((len(p), len(t))) for t, p, _ in binned]
    num_truth = int(sum(len(t) for t, _, _ in binned))
    result: dict = {"num_truth": num_truth, "num_predictions": len(confidence)}
    aps = []
    for th in thresholds_m:
        tp = np.concatenate([_greedy_match(d, rank[a:b], th) for d, a, b in zip(dists, starts[:-1], starts[1:])]
                            ) if binned else np.zeros(0, dtype=bool)
        aps.append(average_precision(confidence, tp, num_truth) if num_truth else None)
        result[f"AP@{th:g}"] = aps[-1]
    result["mAP"] = float(np.mean(aps)) if num_truth else None
    return result


def center_distance_ap(frames: Sequence[Frame], thresholds_m: Sequence[float] = DEFAULT_THRESHOLDS_M,
                       range_bins_m: Sequence[tuple[float, float]] = DEFAULT_RANGE_BINS_M) -> dict:
    """nuScenes-style centre-distance mAP (as in OTVIC, seed 002 Sec. V-B, Table III).

    frames: (truth, predictions) pairs, both in base_link (ego at the origin) at one time;
    predictions are ranked by ``confidence`` over all frames. Class-agnostic: any prediction
    may match any truth (``cls`` is ignored); for a per-class AP, filter the frames by class
    and average the results (OTVIC's mAP is that mean over thresholds and classes).

    Convention (nuscenes-devkit >= 1.0, ``accumulate`` + ``calc_ap``): greedy matching in
    descending confidence, each truth matched at most once, a match iff centre distance
    < threshold (strict); precision linearly interpolated on 101 recall points; AP over the
    points with recall > 0.1, precision clipped at 0.1 and renormalised (``average_precision``).
    mAP = mean of AP over ``thresholds_m``.

    Range bins [lo, hi) m: truths and predictions are each kept by their own distance to
    the ego (nuScenes' ``filter_eval_boxes`` does the same by ego distance), so a prediction
    just across a bin edge from its truth counts as a false positive in one bin and a miss
    in the other.

    Returns {bin label: {"mAP", "AP@<th>" per threshold, "num_truth", "num_predictions"}},
    labels "overall" for (0, inf) and "<lo>-<hi>m" otherwise; AP and mAP are None for a bin
    without truth (nuScenes scores that 0; undefined is the honest value).
    """
    return {bin_label(lo, hi): _bin_ap(_bin_frames(frames, lo, hi), thresholds_m) for lo, hi in range_bins_m}


# --- MOT metrics --------------------------------------------------------------------------

MotFrame = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # truth ids, truth xy, hyp ids, hyp xy


def _distance_matrix(truth_xy: np.ndarray, hyp_xy: np.ndarray, max_distance_m: float) -> np.ndarray:
    """(N, M) Euclidean distances (m); NaN (= may not pair, in motmetrics) beyond max_distance_m."""
    truth_xy = np.asarray(truth_xy, dtype=float).reshape(-1, 2)
    hyp_xy = np.asarray(hyp_xy, dtype=float).reshape(-1, 2)
    if not len(truth_xy) or not len(hyp_xy):
        return np.full((len(truth_xy), len(hyp_xy)), np.nan)
    d = cdist(truth_xy, hyp_xy)
    d[d > max_distance_m] = np.nan
    return d


def _finite_or_none(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def mot_metrics(frames_with_ids: Sequence[MotFrame], max_distance_m: float = 2.0) -> dict:
    """CLEAR-MOT and identity metrics of tracks against ground truth, via ``motmetrics``.

    Each frame: truth ids (N,), truth xy (N, 2) m, hypothesis ids (M,), hypothesis xy (M, 2) m.
    A truth and a hypothesis may pair when their centre distance <= max_distance_m.
        MOTA = 1 - (misses + false positives + id switches) / number of truth objects
        IDF1 = 2 IDTP / (2 IDTP + IDFP + IDFN)  (global one-to-one track-identity matching)
        MOTP = mean centre distance of the matched pairs (m)
    motmetrics 1.4.0 runs on numpy 2 for this use (MOTAccumulator and metrics.compute);
    only its ``distances.iou_matrix`` calls the removed ``np.asfarray``, and it is not used.
    MOTA / IDF1 / MOTP are None when undefined (no truth, no match).
    """
    import motmetrics as mm  # imported here: pandas-heavy, only needed by this metric

    acc = mm.MOTAccumulator(auto_id=True)
    for truth_ids, truth_xy, hyp_ids, hyp_xy in frames_with_ids:
        acc.update(np.asarray(truth_ids).tolist(), np.asarray(hyp_ids).tolist(),
                   _distance_matrix(truth_xy, hyp_xy, max_distance_m))
    names = ["mota", "idf1", "motp", "num_switches", "num_frames", "num_misses", "num_false_positives", "num_objects"]
    row = mm.metrics.create().compute(acc, metrics=names, name="run").iloc[0]
    return {
        "mota": _finite_or_none(row["mota"]), "idf1": _finite_or_none(row["idf1"]),
        "motp_m": _finite_or_none(row["motp"]), "id_switches": int(row["num_switches"]),
        "num_frames": int(row["num_frames"]), "misses": int(row["num_misses"]),
        "false_positives": int(row["num_false_positives"]), "num_truth": int(row["num_objects"]),
    }


# --- NEES ---------------------------------------------------------------------------------

def nees(errors: np.ndarray, covariances: np.ndarray, confidence: float = 0.95) -> dict:
    """Normalised estimation error squared of K 2-D position estimates.

    errors (K, 2) m = estimate - truth; covariances (K, 2, 2) m^2 = the filter's claimed P.
        eps_k = e_k^T P_k^-1 e_k ~ chi2(2) if the filter is consistent (E[eps] = 2)
    ``fraction_inside``: share of eps_k inside the two-sided ``confidence`` interval of chi2(2)
    (about ``confidence`` for an honest filter; lower when P is too small or too large).
    ``mean_interval``: the same interval for the mean (Bar-Shalom's ANEES test:
    K * mean(eps) ~ chi2(2K) for independent samples), ``consistent`` = mean inside it.
    """
    e = np.asarray(errors, dtype=float).reshape(-1, 2)
    if not len(e):
        return {"mean": None, "fraction_inside": None, "interval": None, "mean_interval": None,
                "consistent": None, "samples": 0}
    p = np.asarray(covariances, dtype=float).reshape(-1, 2, 2)
    eps = np.einsum("ki,ki->k", e, np.linalg.solve(p, e[:, :, None])[:, :, 0])  # e^T P^-1 e
    tail = (1.0 - confidence) / 2.0
    lo, hi = chi2.ppf([tail, 1.0 - tail], df=2)
    k = len(eps)
    mean_lo, mean_hi = chi2.ppf([tail, 1.0 - tail], df=2 * k) / k
    mean = float(eps.mean())
    return {
        "mean": mean, "fraction_inside": float(np.mean((eps >= lo) & (eps <= hi))),
        "interval": (float(lo), float(hi)), "mean_interval": (float(mean_lo), float(mean_hi)),
        "consistent": bool(mean_lo <= mean <= mean_hi), "samples": k,
    }
