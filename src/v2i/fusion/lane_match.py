"""The lane predictor's compiled loops: its segment match (``LanePredictor.match``) and its centreline
points (``chain_frame``'s lookups).

Per object i and centreline segment j (start a_j, unit tangent t_j, length L_j, half widths
[left, right], heading psi_j, midpoint m_j), in the numpy expression's float64 operations and order:

    candidate:  (x_i - m_jx)^2 + (y_i - m_jy)^2 <= reach_sq_j          (else cost inf)
    rel = p_i - a_j,  along = rel_x t_x + rel_y t_y,  lateral = t_x rel_y - t_y rel_x   (left positive)
    dist = hypot(along - clip(along, 0, L_j), lateral),  w = left if lateral >= 0 else right
    dpsi = wrap(heading_i - psi_j) = (heading_i - psi_j + pi) mod 2 pi - pi
    ok = dist <= w + margin, |dpsi| <= tolerance, not before a first / after a last segment, road class
    cost = (dist / w)^2 + (dpsi / scale)^2 if ok else inf

and the best segment by numpy's ``argmin`` rule (the first NaN, else the first lowest; every cost inf:
segment 0). That numpy expression is ``match_reference`` (tests/unit/test_lane_match.py: bit for bit on
every bundled map). The headings (arctan2) stay with numpy: its SIMD transcendental functions may
differ from libm's in the last bit.

``chain_frame_points``: ``lane_prediction.chain_points`` of s, s + b and s - b at once (a binary search of
numpy's ``searchsorted(side="right")``, the vertex clipped to the chain, then c = v + (s - cum) t),
the same float64 operations (tests/unit/test_lane_match.py).
"""

from __future__ import annotations

import math

import numpy as np
from numba import types

from v2i.core.frames import wrap_angle
from v2i.core.jit import F64, IN_F1, IN_F2, IN_I1, IN_I2, OUT_F1, OUT_F3, OUT_I1, helper, kernel

IN_B1 = types.Array(types.boolean, 1, "A", readonly=True)

# columns of the segment table (S, 12)
MID_X, MID_Y, REACH_SQ, A_X, A_Y, T_X, T_Y, LENGTH, HALF_LEFT, HALF_RIGHT, PSI, S0 = range(12)
# columns of the segment index table (S, 3)
LANE, FIRST, LAST = range(3)
EDGE_M = 1e-6  # a first (last) segment does not reach before its start (after its end) by more


@helper
def _clip(value: float, high: float) -> float:
    """``np.clip(value, 0.0, high)`` of floats: numpy's max then min, a NaN kept (max(+-0, 0) is +0)."""
    if math.isnan(value):
        return value
    low_clipped = value if value > 0.0 else 0.0
    return low_clipped if low_clipped < high else high


@kernel(IN_F2, IN_F1, IN_B1, IN_F2, IN_I2, IN_F1, OUT_I1, OUT_F1, OUT_F1)
def match_segments(xy: np.ndarray, heading: np.ndarray, road: np.ndarray, seg: np.ndarray, seg_index: np.ndarray,
                   rules: np.ndarray, lane: np.ndarray, s0: np.ndarray, d0: np.ndarray) -> None:
    """Lane (N,) (-1 unmatched), arc length s0 (N,) m and lateral offset d0 (N,) m of objects at ``xy``
    (N, 2) m with ``heading`` (N,) rad and ``road`` (N,) class flags, against the segment tables
    ``seg`` (S, 12) and ``seg_index`` (S, 3); ``rules`` [margin m, tolerance rad, scale rad]."""
    n = xy.shape[0]  # the loop reads and writes without bounds checks: the lengths are checked here
    if not (xy.shape[1] >= 2 and len(heading) == len(road) == len(lane) == len(s0) == len(d0) == n):
        raise ValueError("match_segments: xy (N, 2), heading, road, lane, s0, d0 (N,)")
    if not (seg.shape[1] == 12 and seg_index.shape[1] == 3 and seg_index.shape[0] == seg.shape[0] and len(rules) == 3):
        raise ValueError("match_segments: seg (S, 12), seg_index (S, 3), rules (3,)")
    margin, tolerance, scale = rules[0], rules[1], rules[2]
    for i in range(n):
        x, y = xy[i, 0], xy[i, 1]
        best, best_cost, best_along, best_lateral = 0, math.inf, 0.0, 0.0
        for j in range(seg.shape[0]):
            off_x, off_y = x - seg[j, MID_X], y - seg[j, MID_Y]
            if not off_x * off_x + off_y * off_y <= seg[j, REACH_SQ]:
                continue
            rel_x, rel_y = x - seg[j, A_X], y - seg[j, A_Y]
            t_x, t_y, length = seg[j, T_X], seg[j, T_Y], seg[j, LENGTH]
            along = rel_x * t_x + rel_y * t_y
            lateral = t_x * rel_y - t_y * rel_x
            dist = math.hypot(along - _clip(along, length), lateral)
            half_w = seg[j, HALF_LEFT] if lateral >= 0.0 else seg[j, HALF_RIGHT]
            dpsi = (heading[i] - seg[j, PSI] + math.pi) % (2.0 * math.pi) - math.pi
            ok = dist <= half_w + margin and abs(dpsi) <= tolerance and road[i]
            ok = ok and not (seg_index[j, FIRST] and along < -EDGE_M) and not (seg_index[j, LAST] and along > length + EDGE_M)
            if not ok:
                continue
            q_d, q_psi = dist / half_w, dpsi / scale
            cost = q_d * q_d + q_psi * q_psi
            if math.isnan(cost) or cost < best_cost:  # numpy's argmin: the first NaN, else the first lowest
                best, best_cost, best_along, best_lateral = j, cost, along, lateral
                if math.isnan(cost):
                    break
        if math.isinf(best_cost) or math.isnan(best_cost):  # np.isfinite(cost[best]) fails: unmatched
            lane[i], s0[i], d0[i] = -1, 0.0, 0.0
        else:
            lane[i] = seg_index[best, LANE]
            s0[i] = seg[best, S0] + _clip(best_along, seg[best, LENGTH])
            d0[i] = best_lateral


@kernel(IN_F1, IN_I1, IN_I1, IN_F2, IN_F1, IN_F2, F64, IN_I1, IN_F2, F64, OUT_F3)
def chain_frame_points(key: np.ndarray, first: np.ndarray, last: np.ndarray, vertex: np.ndarray, cum: np.ndarray,
                       tangent: np.ndarray, span: float, chain: np.ndarray, s: np.ndarray, base: float,
                       out: np.ndarray) -> None:
    """Centreline points ``out`` (P, 3 T, 2) m at s, s + base, s - base (each (P, T) m; columns 0..T-1,
    T..2T-1, 2T..3T-1) on ``chain`` (P,), of the chain table (``lane_prediction._Chains``: vertex keys
    (M,) sorted, first / last vertex per chain, vertices, arc lengths and tangents)."""
    p_n, t_n, m = s.shape[0], s.shape[1], len(key)  # checked: the loop reads without bounds checks
    if not (len(chain) == out.shape[0] == p_n and out.shape[1] == 3 * t_n and out.shape[2] == 2):
        raise ValueError("chain_frame_points: chain (P,), s (P, T), out (P, 3 T, 2)")
    if not (len(cum) == vertex.shape[0] == tangent.shape[0] == m and len(first) == len(last)):
        raise ValueError("chain_frame_points: key, cum, vertex, tangent of one length; first, last of one")
    for p in range(p_n):
        c = chain[p]
        if not 0 <= c < len(first) or not 0 <= first[c] < last[c] < m:
            raise ValueError("chain_frame_points: a chain outside the table")
        offset = c * span  # (chain * span): the chain's key offset
        for part in range(3):
            for t in range(t_n):
                s_pt = s[p, t] if part == 0 else s[p, t] + base if part == 1 else s[p, t] - base
                q = s_pt + offset
                lo, hi = 0, m  # searchsorted(key, q, side="right"): the first key > q (NaN: past the end)
                while lo < hi:
                    mid = (lo + hi) >> 1
                    if q < key[mid]:
                        hi = mid
                    else:
                        lo = mid + 1
                j = max(lo - 1, first[c])  # np.clip(j, first, last - 1)
                j = min(j, last[c] - 1)
                along = s_pt - cum[j]
                out[p, part * t_n + t, 0] = vertex[j, 0] + along * tangent[j, 0]
                out[p, part * t_n + t, 1] = vertex[j, 1] + along * tangent[j, 1]


def match_reference(config, seg, map_classes: np.ndarray, objs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``LanePredictor.match`` by the numpy expression of the module docstring, the candidate pairs as arrays:
    ``match_segments``' plain reference (on the matches of whole evals 7-12x slower: 29.5 against 2.6 ms per
    connected-intersection run, 25.0 against 3.0 ms per highway-merge). ``config``: the predictor's
    LanePredictorConfig, ``seg``: its segments (``LanePredictor._seg``), ``map_classes``: the classes on the map;
    objs: an ObjectArray."""
    n = len(objs)
    if n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
    moving = np.hypot(objs.vxy[:, 0], objs.vxy[:, 1]) > config.min_speed_for_heading_mps
    heading = np.where(moving, np.arctan2(objs.vxy[:, 1], objs.vxy[:, 0]), objs.yaw)
    off_x, off_y = np.subtract.outer(objs.xy[:, 0], seg.mid[:, 0]), np.subtract.outer(objs.xy[:, 1], seg.mid[:, 1])
    row, k = np.nonzero(off_x * off_x + off_y * off_y <= seg.reach_sq)
    if not len(row):
        return np.full(n, -1, dtype=seg.lane.dtype), np.zeros(n), np.zeros(n)
    rel = objs.xy[row] - seg.a[k]
    t, length, hw = seg.t[k], seg.length[k], seg.half_w[k]
    along = rel[:, 0] * t[:, 0] + rel[:, 1] * t[:, 1]
    lateral = t[:, 0] * rel[:, 1] - t[:, 1] * rel[:, 0]
    dist = np.hypot(along - np.clip(along, 0.0, length), lateral)
    half_w = np.where(lateral >= 0.0, hw[:, 0], hw[:, 1])
    dpsi = wrap_angle(heading[row] - seg.psi[k])
    ok = (dist <= half_w + config.lateral_margin_m) & (np.abs(dpsi) <= config.heading_tolerance_rad)
    ok &= ~(seg.first[k] & (along < -EDGE_M)) & ~(seg.last[k] & (along > length + EDGE_M))
    ok &= np.isin(objs.cls, map_classes)[row]
    cost = np.full((n, len(seg.lane)), np.inf)
    cost[row, k] = np.where(ok, (dist / half_w) ** 2 + (dpsi / config.heading_scale_rad) ** 2, np.inf)
    best = np.argmin(cost, axis=1)
    rows = np.arange(n)
    matched = np.isfinite(cost[rows, best])
    key = row * len(seg.lane) + k
    at = np.minimum(np.searchsorted(key, rows * len(seg.lane) + best), len(key) - 1)
    lane = np.where(matched, seg.lane[best], -1)
    s0 = seg.s0[best] + np.clip(along[at], 0.0, seg.length[best])
    return lane, np.where(matched, s0, 0.0), np.where(matched, lateral[at], 0.0)
