"""2-D line of sight in the ground plane (bird's-eye view).

A target is sampled at its centre, 4 corners and (optionally) 4 edge midpoints; a sample is
visible when the segment origin -> sample crosses no occluder. Occluders are rotated boxes
(slab test in each box's own frame), polygons (edge crossings + containment) and, optionally,
the other targets' boxes (never the target itself).

Pruning (``PRUNE``): an occluder is tested exactly only against the segments that pass its
bounding circle, found by bearing and range (points sorted by bearing, one ``searchsorted`` per
occluder); the rest cannot hit it. ``PRUNE = False`` tests every segment against every
occluder (the reference, equal to the pruned result; ``benchmarks/eval_speed.py --reference``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fusion.objects import ObjectArray

PRUNE = True  # False: every segment against every occluder (the reference the pruned test equals)
# At most this many (point, box) pairs: every pair through the pruned path's own exact tests
# (pair_hits_boxes, segments_hit_polygons) without the bearing search, cheaper for a few targets
# and occluders (a pair the search would drop cannot hit: the same answers).
SMALL_PAIRS = 1024
_MARGIN_M = 1e-6  # bounding circles grow by this, and
_MARGIN_RAD = 1e-9  # bearing spans by this, so that rounding never prunes a true hit

# Sample offsets in units of (l/2, w/2) in the box frame: centre, corners, edge midpoints.
_OFFSETS = {
    1: np.array([[0.0, 0.0]]),
    5: np.array([[0, 0], [1, 1], [1, -1], [-1, -1], [-1, 1]], dtype=float),
    9: np.array([[0, 0], [1, 1], [1, -1], [-1, -1], [-1, 1], [1, 0], [0, -1], [-1, 0], [0, 1]], dtype=float),
}


def _rot(yaw: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 2, 2) for yaws (N,)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def box_points(xy: np.ndarray, lw: np.ndarray, yaw: np.ndarray, samples: int = 5) -> np.ndarray:
    """Sample points (N, S, 2) of boxes: centres (N, 2), sizes (N, 2) [l, w], yaws (N,).

    S = 1 (centre), 5 (+ corners CCW from front-left) or 9 (+ edge midpoints).
    """
    if samples not in _OFFSETS:
        raise ValueError(f"samples must be one of {sorted(_OFFSETS)}, got {samples}")
    local = _OFFSETS[samples][None] * (np.asarray(lw, dtype=float)[:, None, :] / 2.0)  # (N, S, 2)
    # p = c + R(yaw) q
    return np.asarray(xy, dtype=float)[:, None, :] + np.einsum("nij,nsj->nsi", _rot(np.asarray(yaw)), local)


def segments_hit_boxes(a: np.ndarray, b: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(Q, B) bool: segment a[q] -> b[q] (Q, 2) intersects box [x, y, l, w, yaw] (B, 5).

    Slab test in each box's frame: q(t) = R^T (a - c) + t R^T (b - a), t in [0, 1], inside
    |q_x| <= l/2 and |q_y| <= w/2; per axis t in [(-h - q0)/d, (h - q0)/d] (sorted), the
    segment hits when max over axes of the entries <= min over axes of the exits, clipped to [0, 1].
    """
    a, b, boxes = (np.asarray(v, dtype=float) for v in (a, b, boxes))
    if len(a) == 0 or len(boxes) == 0:
        return np.zeros((len(a), len(boxes)), dtype=bool)
    rot = _rot(boxes[:, 4])  # (B, 2, 2)
    q0 = np.einsum("bji,qbj->qbi", rot, a[:, None, :] - boxes[None, :, :2])  # R^T (a - c)
    d = np.einsum("bji,qj->qbi", rot, b - a)  # R^T (b - a)
    return _slab_hits(q0, d, boxes[None, :, 2:4] / 2.0)


def pair_hits_boxes(origin_xy: np.ndarray, pts: np.ndarray, boxes: np.ndarray, q: np.ndarray, k: np.ndarray) -> np.ndarray:
    """(K,) bool: segment origin (2,) -> pts[q] (Q, 2) intersects box boxes[k] (B, 5), per pair
    (q (K,), k (K,)): the slab test of ``segments_hit_boxes``, written out per axis with the
    same operations (R^T v = (c v_x + s v_y, -s v_x + c v_y)), so the same answers bit for bit."""
    c, s, half = np.cos(boxes[:, 4])[k], np.sin(boxes[:, 4])[k], boxes[:, 2:4] / 2.0
    ac, ba = (origin_xy - boxes[:, :2])[k], (pts - origin_xy)[q]  # a - c, b - a
    entries, exits = [], []
    with np.errstate(divide="ignore", invalid="ignore"):
        for q0, d, h in ((c * ac[:, 0] + s * ac[:, 1], c * ba[:, 0] + s * ba[:, 1], half[k, 0]),
                         (-s * ac[:, 0] + c * ac[:, 1], -s * ba[:, 0] + c * ba[:, 1], half[k, 1])):
            t1, t2 = (-h - q0) / d, (h - q0) / d
            entries.append(np.minimum(t1, t2))
            exits.append(np.maximum(t1, t2))
    enter, leave = np.maximum(*entries), np.minimum(*exits)
    return np.maximum(enter, 0.0) <= np.minimum(leave, 1.0)


def _slab_hits(q0: np.ndarray, d: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(...) bool from start points q0 (..., 2) and directions d (..., 2) in box frames, half sizes (..., 2)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - q0) / d, (half - q0) / d  # d = 0: +-inf if inside the slab, same sign if not
    lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
    enter = np.maximum(lo[..., 0], lo[..., 1])  # the latest entry over the two slabs
    leave = np.minimum(hi[..., 0], hi[..., 1])  # the earliest exit
    return np.maximum(enter, 0.0) <= np.minimum(leave, 1.0)


def cone_pairs(origin_xy: np.ndarray, pts: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Candidate pairs: point indices (K,) and circle indices (K,) such that the segment
    origin (2,) -> pts[k] (Q, 2) may meet the circle (centres (C, 2), radii (C,) m); every
    segment that meets a circle is among them.

    A circle at distance D > r from the origin spans the bearings theta_c +- asin(r / D) (a ray
    at angle phi from the centre's bearing passes at D sin(phi) from it), and a segment reaches it
    only if its length is >= D - r. A circle around the origin (D <= r) keeps every point.
    Circles grow by ``_MARGIN_M`` and spans by ``_MARGIN_RAD`` so that rounding never drops a hit.
    """
    rel, crel = pts - origin_xy, centres - origin_xy
    bearing, length = np.arctan2(rel[:, 1], rel[:, 0]), np.hypot(rel[:, 0], rel[:, 1])
    order = np.argsort(bearing, kind="stable")
    c_bearing, c_dist, r = np.arctan2(crel[:, 1], crel[:, 0]), np.hypot(crel[:, 0], crel[:, 1]), radii + _MARGIN_M
    around = c_dist <= r
    with np.errstate(divide="ignore", invalid="ignore"):
        span = np.where(around, np.inf, np.arcsin(np.minimum(r / c_dist, 1.0)) + _MARGIN_RAD)
    lo, hi = c_bearing - span, c_bearing + span
    # bearing intervals in [-pi, pi]: the main one, and the part wrapped past -pi or +pi (span <= pi/2)
    circle = np.arange(len(centres))
    wrap_lo, wrap_hi = (lo < -np.pi) & ~around, (hi > np.pi) & ~around
    starts = np.concatenate([np.maximum(lo, -np.pi), lo[wrap_lo] + 2 * np.pi, np.full(wrap_hi.sum(), -np.pi)])
    ends = np.concatenate([np.minimum(hi, np.pi), np.full(wrap_lo.sum(), np.pi), hi[wrap_hi] - 2 * np.pi])
    owner = np.concatenate([circle, circle[wrap_lo], circle[wrap_hi]])
    sorted_bearing = bearing[order]
    first = np.searchsorted(sorted_bearing, starts, side="left")
    count = np.maximum(np.searchsorted(sorted_bearing, ends, side="right") - first, 0)
    # ranges [first, first + count) of the sorted points -> flat indices
    offset = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    point, circ = order[np.repeat(first, count) + offset], np.repeat(owner, count)
    reach = length[point] >= c_dist[circ] - r[circ] - _MARGIN_M
    return point[reach], circ[reach]


def _edges(polygons: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All polygon edges: starts (E, 2), ends (E, 2), index of each polygon's first edge (P,)."""
    polys = [np.asarray(p, dtype=float) for p in polygons]
    starts = np.concatenate(polys)
    ends = np.concatenate([np.roll(p, -1, axis=0) for p in polys])
    first = np.cumsum([0] + [len(p) for p in polys[:-1]])
    return starts, ends, first


def _cross(o: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """z of (p - o) x (q - o), broadcast over leading axes."""
    return (p[..., 0] - o[..., 0]) * (q[..., 1] - o[..., 1]) - (p[..., 1] - o[..., 1]) * (q[..., 0] - o[..., 0])


def segments_hit_polygons(a: np.ndarray, b: np.ndarray, polygons: Sequence[np.ndarray]) -> np.ndarray:
    """(Q, P) bool: segment a[q] -> b[q] (Q, 2) intersects simple polygon p, each (K_p, 2).

    Hit = the segment crosses an edge (orientation test: each segment's end points lie on
    opposite sides of the other) or lies inside (end point b inside, crossing-number test).
    """
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if len(a) == 0 or len(polygons) == 0:
        return np.zeros((len(a), len(polygons)), dtype=bool)
    c, d, first = _edges(polygons)
    A, B, C, D = a[:, None], b[:, None], c[None], d[None]
    crosses = (_cross(A, B, C) * _cross(A, B, D) <= 0) & (_cross(C, D, A) * _cross(C, D, B) <= 0)
    # ray from b towards +x crosses edge (c, d): c and d straddle b_y and the crossing is right of b
    straddle = (C[..., 1] > B[..., 1]) != (D[..., 1] > B[..., 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = C[..., 0] + (B[..., 1] - C[..., 1]) * (D[..., 0] - C[..., 0]) / (D[..., 1] - C[..., 1])
    ray_hits = straddle & (B[..., 0] < x_at)
    inside = np.add.reduceat(ray_hits.astype(np.int64), first, axis=1) % 2 == 1
    return np.logical_or.reduceat(crosses, first, axis=1) | inside


def visible_fraction(
    origin_xy: np.ndarray,
    targets: ObjectArray,
    occluder_boxes: np.ndarray | None = None,
    polygons: Sequence[np.ndarray] = (),
    samples: int = 9,
    targets_occlude: bool = True,
    sampled: np.ndarray | None = None,
) -> np.ndarray:
    """Fraction (N,) in [0, 1] of each target's sample points seen from ``origin_xy`` (2,) m.

    occluder_boxes (M, 5) [x, y, l, w, yaw rad] and polygons (each (K, 2)) are static
    occluders; with ``targets_occlude`` every other target's box occludes too.
    ``sampled`` (N,) bool: only these targets' points are tested (their fractions are the ones
    testing all would give: each point is tested on its own); the others get 0 and still occlude.
    """
    n = len(targets)
    if n == 0:
        return np.zeros(0)
    origin = np.asarray(origin_xy, dtype=float)
    pts = box_points(targets.xy, targets.lwh[:, :2], targets.yaw, samples).reshape(-1, 2)  # (N S, 2)
    owner = np.repeat(np.arange(n), samples)  # target of each sample point
    if sampled is not None:
        rows = np.repeat(np.asarray(sampled, dtype=bool), samples)
        pts, owner = pts[rows], owner[rows]
    boxes = np.zeros((0, 5)) if occluder_boxes is None else np.asarray(occluder_boxes, dtype=float).reshape(-1, 5)
    if targets_occlude and n > 1:
        boxes = np.concatenate([boxes, np.column_stack([targets.xy, targets.lwh[:, :2], targets.yaw])])
        box_owner = np.concatenate([np.full(len(boxes) - n, -1), np.arange(n)])  # a target never hides itself
    else:
        box_owner = np.full(len(boxes), -1)
    blocked_by = _blocked_all if not PRUNE else _blocked_every_pair if len(pts) * len(boxes) <= SMALL_PAIRS \
        else _blocked_pruned
    blocked = blocked_by(origin, pts, owner, boxes, box_owner, polygons)
    if sampled is None:
        return 1.0 - blocked.reshape(n, samples).mean(axis=1)
    out = np.zeros(n)
    out[np.asarray(sampled, dtype=bool)] = 1.0 - blocked.reshape(-1, samples).mean(axis=1)
    return out


def _blocked_all(origin, pts, owner, boxes, box_owner, polygons) -> np.ndarray:
    """(Q,) bool: segment origin -> pts[q] meets a box not owned by owner[q], or a polygon; all pairs tested."""
    a = np.broadcast_to(origin, pts.shape)
    blocked = np.zeros(len(pts), dtype=bool)
    if len(boxes):
        hits = segments_hit_boxes(a, pts, boxes)
        hits &= box_owner[None, :] != owner[:, None]
        blocked |= hits.any(axis=1)
    if len(polygons):
        blocked |= segments_hit_polygons(a, pts, polygons).any(axis=1)
    return blocked


def _blocked_every_pair(origin, pts, owner, boxes, box_owner, polygons) -> np.ndarray:
    """``_blocked_pruned`` without the pruning: the same exact tests on every (point, occluder) pair."""
    blocked = np.zeros(len(pts), dtype=bool)
    if len(boxes):
        q, k = np.repeat(np.arange(len(pts)), len(boxes)), np.tile(np.arange(len(boxes)), len(pts))
        other = box_owner[k] != owner[q]  # a target never hides itself
        q, k = q[other], k[other]
        blocked[q[pair_hits_boxes(origin, pts, boxes, q, k)]] = True
    for poly in polygons:
        q = np.flatnonzero(~blocked)
        poly = np.asarray(poly, dtype=float)
        blocked[q[segments_hit_polygons(np.broadcast_to(origin, (len(q), 2)), pts[q], [poly])[:, 0]]] = True
    return blocked


def _blocked_pruned(origin, pts, owner, boxes, box_owner, polygons) -> np.ndarray:
    """``_blocked_all``, testing exactly only the pairs whose bounding circles ``cone_pairs`` keeps
    (one ``cone_pairs`` over the boxes' and the polygons' circles: a pair's fate is its own)."""
    blocked = np.zeros(len(pts), dtype=bool)
    polys = [np.asarray(poly, dtype=float) for poly in polygons]
    if not len(boxes) and not polys:
        return blocked
    centres = [(poly.min(axis=0) + poly.max(axis=0)) / 2.0 for poly in polys]
    radii = [np.hypot(*(poly - centre).T).max() for poly, centre in zip(polys, centres)]
    q_all, k_all = cone_pairs(origin, pts, np.concatenate([boxes[:, :2], np.reshape(centres, (-1, 2))]),
                              np.concatenate([np.hypot(boxes[:, 2], boxes[:, 3]) / 2.0, radii]))
    if len(boxes):
        is_box = k_all < len(boxes)
        q, k = q_all[is_box], k_all[is_box]
        other = box_owner[k] != owner[q]  # a target never hides itself
        q, k = q[other], k[other]
        hit = pair_hits_boxes(origin, pts, boxes, q, k)
        blocked[q[hit]] = True
    for j, poly in enumerate(polys):
        q = q_all[k_all == len(boxes) + j]
        q = q[~blocked[q]]
        blocked[q[segments_hit_polygons(np.broadcast_to(origin, (len(q), 2)), pts[q], [poly])[:, 0]]] = True
    return blocked
