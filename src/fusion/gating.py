"""Gating and assignment of detections to tracks (the association step of ``fusion.tracking``).

A pair (track, detection) is allowed when the classes are compatible (equal, or either is
UNKNOWN = 0) and the pair passes the gate (``TrackerConfig.gate``): ``distance``: centre
distance <= gate_m; ``mahalanobis``: d2 = y^T S^-1 y <= gate_chi2 with y = z - H x,
S = H P H^T + R; ``either``: one of the two, within gate_max_m. Among allowed pairs a
minimum-cost one-to-one assignment (``association.assign_sparse``) with cost ``distance``
(m), ``mahalanobis`` (d2) or ``iou`` (1 - BEV IoU of the predicted and the detected box).

Candidates first (``_near``): tracks inside the detections' bounding box grown by the
largest reach any pair can have, then a bound per pair on the (rows, M) block:
distance gate |y| <= gate_m; Mahalanobis gate d2 = y^T S^-1 y >= |y|^2 / lambda_max(S) and
lambda_max(S) <= tr(S) = tr(H P H^T) + tr(R), so a pair with |y|^2 > chi2 (tr P_xy + tr R)
fails. The exact test (and the class check, in the same pass) then runs on the few pairs left,
with the offsets of the bound (y = -(x_track - z), exactly) and the 2 x 2 entries of S gathered per pair.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import shapely

from . import kalman
from .association import Assignment, assign_sparse
from .fastnp import true_index
from .geometry import box_polygons
from .objects import ObjectArray

if TYPE_CHECKING:
    from .track_table import TrackTable
    from .tracking import TrackerConfig

_NO_INDEX = np.zeros(0, np.int64)


@dataclass(frozen=True)
class GatedPairs:
    """K (track, detection) pairs inside the gate and class-compatible, with their cost (K,)."""

    track: np.ndarray
    det: np.ndarray
    cost: np.ndarray


def compatible_classes(track_cls: np.ndarray, det_cls: np.ndarray) -> np.ndarray:
    """True where classes are equal or either is UNKNOWN (0); paired arrays or broadcast (N, 1), (1, M).
    Either is 0 exactly when the product is (integer class codes, far from overflowing: ObjectClass < 256)."""
    return (track_cls == det_cls) | (track_cls * det_cls == 0)


def _trace2(c: np.ndarray) -> np.ndarray:
    """Trace of 2 x 2 covariances (K, 2, 2): an upper bound of their largest eigenvalue."""
    return c[:, 0, 0] + c[:, 1, 1]


def _near(config: TrackerConfig, table: TrackTable, dets: ObjectArray):
    """Candidate pairs (module docstring): track ti (K,) and detection di (K,) of each pair inside the
    bound (ordered by track, then detection; classes not yet compared), and their offsets dx, dy (K,) =
    track - detection."""
    x, dxy = table.x, dets.xy
    px, py, zx, zy = x[:, 0], x[:, 1], dxy[:, 0], dxy[:, 1]
    reach_m, lam_p = config.gate_m, None
    # (ufunc reductions on columns, Python floats: the array methods and (M, 2) reductions cost more)
    if config.gate != "distance":
        lam_p, lam_r = _trace2(table.p), _trace2(dets.cov_xy)
        reach_m = math.sqrt(config.gate_chi2 * (float(np.maximum.reduce(lam_p)) + float(np.maximum.reduce(lam_r))))
        if config.gate == "either":
            reach_m = min(max(reach_m, config.gate_m), config.gate_max_m)
    x_lo, x_hi = float(np.minimum.reduce(zx)) - reach_m, float(np.maximum.reduce(zx)) + reach_m
    y_lo, y_hi = float(np.minimum.reduce(zy)) - reach_m, float(np.maximum.reduce(zy)) + reach_m
    rows = true_index((px >= x_lo) & (px <= x_hi) & (py >= y_lo) & (py <= y_hi))
    dx, dy = np.subtract.outer(px.take(rows), zx), np.subtract.outer(py.take(rows), zy)
    r2 = dx * dx
    r2 += dy * dy
    if config.gate == "distance":
        near = r2 <= config.gate_m**2
    else:
        near = r2 <= config.gate_chi2 * np.add.outer(lam_p.take(rows), lam_r)
        if config.gate == "either":
            near = (r2 <= config.gate_m**2) | (near & (r2 <= config.gate_max_m**2))
    flat = true_index(near)  # row-major, as np.nonzero (which is slower on 2-D arrays)
    tl, di = np.divmod(flat, near.shape[1])
    return rows.take(tl), di, dx.ravel().take(flat), dy.ravel().take(flat)


def gated_pairs(config: TrackerConfig, table: TrackTable, dets: ObjectArray) -> GatedPairs:
    """Class-compatible pairs inside the configured gate with the configured cost (module docstring)."""
    if not len(table) or not len(dets):
        return GatedPairs(_NO_INDEX, _NO_INDEX, np.zeros(0))
    ti, di, dx, dy = _near(config, table, dets)
    if config.gate != "mahalanobis" or config.cost == "distance":
        dist = np.hypot(dx, dy)  # |y|, y = z - H x = -(dx, dy)
    if config.gate != "distance" or config.cost == "mahalanobis":
        s = table.p.take(ti, axis=0)[:, :2, :2] + dets.cov_xy.take(di, axis=0)  # S = H P H^T + R per pair, d2 = y^T S^-1 y
        d2 = kalman._quadratic_form(dx, dy, s[:, 0, 0], s[:, 0, 1], s[:, 1, 0], s[:, 1, 1])
    if config.gate == "distance":
        inside = dist <= config.gate_m
    elif config.gate == "mahalanobis":
        inside = d2 <= config.gate_chi2
    else:
        inside = (dist <= config.gate_m) | ((d2 <= config.gate_chi2) & (dist <= config.gate_max_m))
    inside = true_index(inside & compatible_classes(table.cls.take(ti), dets.cls.take(di)))
    ti, di = ti.take(inside), di.take(inside)
    if config.cost == "distance":
        cost = dist.take(inside)
    elif config.cost == "mahalanobis":
        cost = d2.take(inside)
    else:  # 1 - BEV IoU of the predicted box (last detected size and yaw) and the detected box
        a = np.column_stack([table.x[ti, :2], table.lwh[ti, :2], table.yaw[ti]])
        cost = 1.0 - paired_bev_iou(a, np.column_stack([dets.xy[di], dets.lwh[di, :2], dets.yaw[di]]))
    return GatedPairs(ti, di, cost)


def paired_bev_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU (K,) of paired BEV boxes a[k], b[k] (K, 5) [x, y, l, w, yaw]: |A n B| / (|A| + |B| - |A n B|).

    Polygons from ``fusion.geometry``; one intersection per pair instead of a whole matrix.
    """
    if not len(a):
        return np.zeros(0)
    inter = shapely.area(shapely.intersection(box_polygons(a), box_polygons(b)))
    union = a[:, 2] * a[:, 3] + b[:, 2] * b[:, 3] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def assign_pairs(pairs: GatedPairs, n_tracks: int, n_dets: int) -> Assignment:
    """Minimum-cost one-to-one matching among the gated pairs (``association.assign_sparse``:
    per connected component of the gated graph, scipy linear_sum_assignment for those of more than one pair)."""
    return assign_sparse(pairs.track, pairs.det, pairs.cost, n_tracks, n_dets)


def associate(config: TrackerConfig, table: TrackTable, dets: ObjectArray) -> Assignment:
    """Gate, cost and assign the detections to the tracks (indices into table and dets)."""
    return assign_pairs(gated_pairs(config, table, dets), len(table), len(dets))


def association_cost(config: TrackerConfig, table: TrackTable, dets: ObjectArray) -> np.ndarray:
    """Dense cost (N tracks, M detections) of the gated pairs; inf elsewhere."""
    pairs = gated_pairs(config, table, dets)
    cost = np.full((len(table), len(dets)), np.inf)
    cost[pairs.track, pairs.det] = pairs.cost
    return cost


def assign_gated(cost: np.ndarray) -> Assignment:
    """Minimum-cost one-to-one matching among the finite entries of a dense cost (N, M)."""
    ti, di = np.nonzero(np.isfinite(cost))
    return assign_pairs(GatedPairs(ti, di, cost[ti, di]), *cost.shape)
