"""Gating and assignment of detections to tracks (the association step of ``v2i.fusion.tracking``).

A pair (track, detection) is allowed when the classes are compatible (equal, or either is
UNKNOWN = 0) and the pair passes the gate (``TrackerConfig.gate``): ``distance``: centre
distance <= gate_m; ``mahalanobis``: d2 = y^T S^-1 y <= gate_chi2 with y = z - H x,
S = H P H^T + R; ``either``: one of the two, within gate_max_m. Among allowed pairs a
minimum-cost one-to-one assignment (``association.assign_sparse``) with cost ``distance``
(m), ``mahalanobis`` (d2) or ``iou`` (1 - BEV IoU of the predicted and the detected box).

Each pair is tested in one compiled loop over tracks and detections (``_gate_pairs``, numba): a bound
first, distance gate |y| <= gate_m; Mahalanobis gate d2 = y^T S^-1 y >= |y|^2 / lambda_max(S) and
lambda_max(S) <= tr(S) = tr(H P H^T) + tr(R), so a pair with |y|^2 > chi2 (tr P_xy + tr R)
fails. The exact test and the class check run on the pairs the bound leaves. When every gated pair is
a component of its own (most lists), that same call (``_gate_single_pairs``) matches them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from v2i.fusion.association import Assignment, assign_sparse
from v2i.fusion.geometry import iou_rows
from v2i.core.jit import F64, I64, IN_F2, IN_F3, IN_I1, helper, kernel
from v2i.fusion.kalman import mahalanobis_sq
from v2i.core.objects import ObjectArray

if TYPE_CHECKING:
    from v2i.fusion.track_table import TrackTable
    from v2i.fusion.tracking import TrackerConfig

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


_GATES = {"distance": 0, "mahalanobis": 1, "either": 2}  # the kernel's codes of TrackerConfig.gate
_COSTS = {"distance": 0, "mahalanobis": 1, "iou": 2}  # ... and of TrackerConfig.cost (iou: computed afterwards)


def gated_pairs(config: TrackerConfig, table: TrackTable, dets: ObjectArray) -> GatedPairs:
    """Class-compatible pairs inside the configured gate with the configured cost (module docstring),
    ordered by track, then detection."""
    if not len(table) or not len(dets):
        return GatedPairs(_NO_INDEX, _NO_INDEX, np.zeros(0))
    _, pairs, _, _, cost = _gate_single_pairs(table.x, table.p, table.cls, dets.xy, dets.cov_xy, dets.cls,
                                              _GATES[config.gate], _COSTS[config.cost], config.gate_m,
                                              config.gate_chi2, config.gate_max_m)
    return _costed(config, table, dets, pairs[:, 0], pairs[:, 1], cost)


def _costed(config: TrackerConfig, table: TrackTable, dets: ObjectArray, ti: np.ndarray, di: np.ndarray,
            cost: np.ndarray) -> GatedPairs:
    """The gated pairs (ti, di) with the configured cost: the kernel's (distance, d2), or for ``iou``
    1 - BEV IoU of the predicted box (last detected size and yaw) and the detected box."""
    if config.cost == "iou":
        a = np.column_stack([table.x[ti, :2], table.lwh[ti, :2], table.yaw[ti]])
        cost = 1.0 - paired_bev_iou(a, np.column_stack([dets.xy[di], dets.lwh[di, :2], dets.yaw[di]]))
    return GatedPairs(ti, di, cost)


@kernel(IN_F2, IN_F3, IN_I1, IN_F2, IN_F3, IN_I1, I64, I64, F64, F64, F64)
def _gate_single_pairs(x: np.ndarray, p: np.ndarray, track_cls: np.ndarray, z: np.ndarray, r: np.ndarray,
                       det_cls: np.ndarray, gate: int, cost: int, gate_m: float, gate_chi2: float, gate_max_m: float):
    """``_gate_pairs`` as (K, 2) [track, detection] rows with their costs (K,), and the matching when every gated
    pair is a component of its own (its track and its detection in no other pair; ``association.assign_sparse``
    matches such a pair as it is): (True, the pairs = the matches, sorted by track; unmatched tracks; unmatched
    detections; the costs), or (False, the pairs, empty, empty, the costs) when some component needs the solver.
    The usual list in one call, returning 4 arrays instead of 8 from 3 kernels."""
    ti, di, out = _gate_pairs(x, p, track_cls, z, r, det_cls, gate, cost, gate_m, gate_chi2, gate_max_m)
    n_t, n_d = x.shape[0], z.shape[0]
    count_t, count_d = np.zeros(n_t, np.int64), np.zeros(n_d, np.int64)
    pairs = np.empty((len(ti), 2), np.int64)  # ti ascending: sorted by track
    single = True
    for k in range(len(ti)):
        count_t[ti[k]] += 1
        count_d[di[k]] += 1
        pairs[k, 0], pairs[k, 1] = ti[k], di[k]
    for k in range(len(ti)):
        if count_t[ti[k]] != 1 or count_d[di[k]] != 1:
            single = False
            break
    if not single:
        return False, pairs, count_t[:0], count_d[:0], out
    return True, pairs, np.flatnonzero(count_t == 0), np.flatnonzero(count_d == 0), out


@helper
def _gate_pairs(x: np.ndarray, p: np.ndarray, track_cls: np.ndarray, z: np.ndarray, r: np.ndarray,
                det_cls: np.ndarray, gate: int, cost: int, gate_m: float, gate_chi2: float, gate_max_m: float):
    """Pairs (ti, di, cost) of tracks x (N, n), P (N, n, n) and detections z (M, 2), R (M, 2, 2) inside the gate
    (``_GATES`` code) and class-compatible, ordered by track then detection, cost by ``_COSTS`` code (0 for iou).

    Per pair, the bound of the module docstring first (|y|^2 against gate_m^2, or against
    chi2 (tr P_xy + tr R) for the Mahalanobis gate, which bounds d2 = y^T S^-1 y <= chi2 from outside),
    then the exact test: |y| = hypot(y) and d2 with S = H P H^T + R in closed form
    (d2 = (s11 y0^2 - (s01 + s10) y0 y1 + s00 y1^2) / det S, ``kalman._quadratic_form``).
    """
    n_t, n_d = x.shape[0], z.shape[0]
    size = 4 * (n_t + n_d)  # doubled when full: a gate passes a few pairs per track, not N x M
    ti, di, out = np.empty(size, np.int64), np.empty(size, np.int64), np.empty(size)
    m2, max2, k = gate_m * gate_m, gate_max_m * gate_max_m, 0
    x_lo, x_hi, y_lo, y_hi = z[0, 0], z[0, 0], z[0, 1], z[0, 1]  # the detections' bounding box
    tr_r_max = 0.0
    for j in range(n_d):
        x_lo, x_hi = min(x_lo, z[j, 0]), max(x_hi, z[j, 0])
        y_lo, y_hi = min(y_lo, z[j, 1]), max(y_hi, z[j, 1])
        tr_r_max = max(tr_r_max, r[j, 0, 0] + r[j, 1, 1])
    for i in range(n_t):
        px, py, tr_p, ct = x[i, 0], x[i, 1], p[i, 0, 0] + p[i, 1, 1], track_cls[i]
        # a track farther from the box than any pair's bound can reach pairs with no detection
        reach = math.sqrt(m2 if gate == 0 else (gate_chi2 * (tr_p + tr_r_max) if gate == 1 else
                                                 max(m2, min(gate_chi2 * (tr_p + tr_r_max), max2))))
        if not (px >= x_lo - reach and px <= x_hi + reach and py >= y_lo - reach and py <= y_hi + reach):
            continue
        for j in range(n_d):
            dx, dy = px - z[j, 0], py - z[j, 1]  # y = -(dx, dy); every form below is even in y
            r2 = dx * dx + dy * dy
            if gate == 0:
                near = r2 <= m2
            else:
                near = r2 <= gate_chi2 * (tr_p + (r[j, 0, 0] + r[j, 1, 1]))
                if gate == 2:
                    near = (r2 <= m2) or (near and r2 <= max2)
            cd = det_cls[j]
            if not near or not (ct == cd or ct * cd == 0):
                continue
            dist = math.hypot(dx, dy)
            s00, s01 = p[i, 0, 0] + r[j, 0, 0], p[i, 0, 1] + r[j, 0, 1]
            s10, s11 = p[i, 1, 0] + r[j, 1, 0], p[i, 1, 1] + r[j, 1, 1]
            d2 = (s11 * dx * dx - (s01 + s10) * dx * dy + s00 * dy * dy) / (s00 * s11 - s01 * s10)
            if gate == 0:
                inside = dist <= gate_m
            elif gate == 1:
                inside = d2 <= gate_chi2
            else:
                inside = dist <= gate_m or (d2 <= gate_chi2 and dist <= gate_max_m)
            if inside:
                if k == len(out):  # full: twice the room
                    ti, di, out = np.concatenate((ti, ti)), np.concatenate((di, di)), np.concatenate((out, out))
                ti[k], di[k] = i, j
                out[k] = dist if cost == 0 else (d2 if cost == 1 else 0.0)
                k += 1
    return ti[:k].copy(), di[:k].copy(), out[:k].copy()


def gated_pairs_reference(config: TrackerConfig, table: TrackTable, dets: ObjectArray):
    """(ti, di, cost) of ``_gate_pairs`` from dense (N, M) matrices: every pair's distance and Mahalanobis
    distance (``kalman.mahalanobis_sq``), the gate and the class rule, in row-major order (its plain
    reference: on the gates of 330 cycle_compute cycles 514 us per gate against the kernel's 12.8 us)."""
    d2 = mahalanobis_sq(table.x, table.p, dets.xy, dets.cov_xy)
    dist = np.hypot(dets.xy[None, :, 0] - table.x[:, None, 0], dets.xy[None, :, 1] - table.x[:, None, 1])
    inside = {"distance": dist <= config.gate_m, "mahalanobis": d2 <= config.gate_chi2,
              "either": (dist <= config.gate_m) | ((d2 <= config.gate_chi2) & (dist <= config.gate_max_m))}
    allowed = inside[config.gate] & compatible_classes(table.cls[:, None], dets.cls[None, :])
    ti, di = np.nonzero(allowed)
    return ti, di, (dist if config.cost == "distance" else d2)[ti, di]


def paired_bev_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU (K,) of paired BEV boxes a[k], b[k] (K, 5) [x, y, l, w, yaw]: |A n B| / (|A| + |B| - |A n B|).

    ``v2i.fusion.geometry.iou_rows``: one intersection per pair instead of a whole matrix.
    """
    return iou_rows(np.asarray(a, dtype=float), np.asarray(b, dtype=float)) if len(a) else np.zeros(0)


def assign_pairs(pairs: GatedPairs, n_tracks: int, n_dets: int) -> Assignment:
    """Minimum-cost one-to-one matching among the gated pairs (``association.assign_sparse``:
    per connected component of the gated graph, ``v2i.fusion.lsap`` for those of more than one pair)."""
    return assign_sparse(pairs.track, pairs.det, pairs.cost, n_tracks, n_dets)


def associate(config: TrackerConfig, table: TrackTable, dets: ObjectArray) -> Assignment:
    """Gate, cost and assign the detections to the tracks (indices into table and dets). When every gated
    pair is a component of its own (most lists), the costs do not matter: one compiled call
    (``_gate_single_pairs``) gates and matches; else the pairs it gated, with their costs, go to ``assign_pairs``."""
    if not len(table) or not len(dets):
        return assign_pairs(gated_pairs(config, table, dets), len(table), len(dets))
    single, pairs, free_t, free_d, cost = _gate_single_pairs(
        table.x, table.p, table.cls, dets.xy, dets.cov_xy, dets.cls, _GATES[config.gate], _COSTS[config.cost],
        config.gate_m, config.gate_chi2, config.gate_max_m)
    if single:
        return Assignment(pairs, free_t, free_d)
    return assign_pairs(_costed(config, table, dets, pairs[:, 0], pairs[:, 1], cost), len(table), len(dets))


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
