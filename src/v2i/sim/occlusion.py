"""2-D line of sight in the ground plane (bird's-eye view).

A target is sampled at its centre, 4 corners and (optionally) 4 edge midpoints; a sample is
visible when the segment origin -> sample crosses no occluder. Occluders are rotated boxes
(slab test in each box's own frame), polygons (edge crossings + containment) and, optionally,
the other targets' boxes (never the target itself).

The test runs compiled (numba, ``_blocked``): per target, its sample points made as ``box_points``
makes them, and per point the occluders one by one until one blocks it. ``COMPILED = False`` runs the numpy reference instead, every segment against
every occluder as (points, occluders) arrays; both give the same answers bit for bit (the same
operations in the same order; tests/unit/test_occlusion_kernel.py,
``benchmarks/eval_speed.py --reference``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from v2i.core.identity_memo import IdentityMemo
from v2i.core.jit import B1, IN_F1, IN_F2, IN_I1, IN_U1, helper, kernel
from v2i.core.objects import ObjectArray

_NO_EDGES = np.zeros(0, np.int64)

REACH_MARGIN_M = 1e-6  # the compiled test skips a box whose circumscribed square, this much larger, misses a segment's box
COMPILED = True  # False: the numpy reference (every segment against every occluder, as arrays)

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


def _slab_hits(q0: np.ndarray, d: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(...) bool from start points q0 (..., 2) and directions d (..., 2) in box frames, half sizes (..., 2)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - q0) / d, (half - q0) / d  # d = 0: +-inf if inside the slab, same sign if not
    lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
    enter = np.maximum(lo[..., 0], lo[..., 1])  # the latest entry over the two slabs
    leave = np.minimum(hi[..., 0], hi[..., 1])  # the earliest exit
    return np.maximum(enter, 0.0) <= np.minimum(leave, 1.0)


def _edges(polygons: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All polygon edges: starts (E, 2), ends (E, 2), index of each polygon's first edge (P,)."""
    polys = [np.asarray(p, dtype=float) for p in polygons]
    starts = np.concatenate(polys)
    ends = np.concatenate([np.roll(p, -1, axis=0) for p in polys])
    first = np.cumsum([0] + [len(p) for p in polys[:-1]])
    return starts, ends, first


_kept_edges = IdentityMemo(_edges, capacity=64)  # of the static occluders: a world's polygons tuple


def _static_edges(polygons: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``_edges``, kept for a tuple of polygons (a world's buildings, the same tuple every frame)."""
    if not len(polygons):
        return np.zeros((0, 2)), np.zeros((0, 2)), _NO_EDGES
    if not isinstance(polygons, tuple):
        return _edges(polygons)
    return _kept_edges(polygons)


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
    if samples not in _OFFSETS:
        raise ValueError(f"samples must be one of {sorted(_OFFSETS)}, got {samples}")
    origin = np.asarray(origin_xy, dtype=float)
    boxes = np.zeros((0, 5)) if occluder_boxes is None else np.asarray(occluder_boxes, dtype=float).reshape(-1, 5)
    if not COMPILED:
        return _visible_fraction_all(origin, targets, boxes, polygons, samples, targets_occlude, sampled)
    wanted = np.ones(n, dtype=bool) if sampled is None else np.asarray(sampled, dtype=bool)
    if wanted.shape != (n,):  # the kernel reads wanted[i] for every target i
        raise ValueError(f"sampled has shape {wanted.shape}, the targets are {n}")
    starts, ends, first = _static_edges(polygons)
    # (cos, sin) of the yaws by numpy, as the reference: the kernel's own could differ in the last bit
    yaw = targets.yaw
    blocked = _blocked(origin, targets.xy, targets.lwh, np.cos(yaw), np.sin(yaw), _OFFSETS[samples], wanted.view(np.uint8),
                       targets_occlude and n > 1, boxes, np.cos(boxes[:, 4]), np.sin(boxes[:, 4]), starts, ends, first)
    fraction = 1.0 - blocked / samples  # the mean of the points' blocked flags: count / samples
    return fraction if sampled is None else np.where(wanted, fraction, 0.0)


def _visible_fraction_all(origin, targets, boxes, polygons, samples, targets_occlude, sampled) -> np.ndarray:
    """``visible_fraction`` by the numpy reference: every sample point against every occluder, as arrays."""
    n = len(targets)
    pts = box_points(targets.xy, targets.lwh[:, :2], targets.yaw, samples).reshape(-1, 2)  # (N S, 2)
    owner = np.repeat(np.arange(n), samples)  # target of each sample point
    if sampled is not None:
        rows = np.repeat(np.asarray(sampled, dtype=bool), samples)
        pts, owner = pts[rows], owner[rows]
    if targets_occlude and n > 1:
        boxes = np.concatenate([boxes, np.column_stack([targets.xy, targets.lwh[:, :2], targets.yaw])])
        box_owner = np.concatenate([np.full(len(boxes) - n, -1), np.arange(n)])  # a target never hides itself
    else:
        box_owner = np.full(len(boxes), -1)
    blocked = _blocked_all(origin, pts, owner, boxes, box_owner, polygons)
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


@kernel(IN_F1, IN_F2, IN_F2, IN_F1, IN_F1, IN_F2, IN_U1, B1, IN_F2, IN_F1, IN_F1, IN_F2, IN_F2, IN_I1)
def _blocked(origin: np.ndarray, xy: np.ndarray, lwh: np.ndarray, cos: np.ndarray, sin: np.ndarray,
             offsets: np.ndarray, wanted: np.ndarray, occlude: bool, boxes: np.ndarray, box_cos: np.ndarray,
             box_sin: np.ndarray, starts: np.ndarray, ends: np.ndarray, first: np.ndarray) -> np.ndarray:
    """Blocked sample points (N,) of each wanted target (``_blocked_all`` compiled, point by point): targets
    xy (N, 2), lwh (N, 3), cos, sin (N,) of their yaws; a point is p = c + R(yaw) q, q = offset (S, 2) *
    (l/2, w/2), with ``box_points``' operations. Each point meets the boxes (M, 5) (box_cos, box_sin (M,)),
    then, with ``occlude``, the other targets' boxes, then the polygons (edges starts / ends (E, 2),
    polygon p's from first[p]), until one blocks it."""
    blocked = np.zeros(len(xy), np.int64)
    box_reach, reach = _reach(boxes[:, 2], boxes[:, 3]), _reach(lwh[:, 0], lwh[:, 1])
    for i in range(len(xy)):
        if not wanted[i]:
            continue
        half_l, half_w = lwh[i, 0] / 2.0, lwh[i, 1] / 2.0
        for k in range(len(offsets)):
            qx, qy = offsets[k, 0] * half_l, offsets[k, 1] * half_w
            px = xy[i, 0] + (cos[i] * qx + (-sin[i]) * qy)  # c + R q, R = [[c, -s], [s, c]]
            py = xy[i, 1] + (sin[i] * qx + cos[i] * qy)
            if _point_blocked(origin, px, py, i, xy, lwh, cos, sin, reach, occlude, boxes, box_cos, box_sin,
                              box_reach, starts, ends, first):
                blocked[i] += 1
    return blocked


@helper
def _reach(length: np.ndarray, width: np.ndarray) -> np.ndarray:
    """(B,) m: half the diagonal of each box (l, w (B,)) plus REACH_MARGIN_M: no point of the box is farther
    from its centre."""
    out = np.empty(len(length))
    for k in range(len(length)):
        out[k] = 0.5 * np.sqrt(length[k] * length[k] + width[k] * width[k]) + REACH_MARGIN_M
    return out


@helper
def _apart(a: np.ndarray, px: float, py: float, x: float, y: float, reach: float) -> bool:
    """The segment a -> (px, py) cannot meet the box centred at (x, y) of that reach: the square of side
    2 reach around the centre lies outside the segment's bounding box (the slab test finds no hit either:
    its rounding is ~1e-13 m, far below REACH_MARGIN_M)."""
    return (x - reach > max(a[0], px) or x + reach < min(a[0], px) or y - reach > max(a[1], py)
            or y + reach < min(a[1], py))


@helper
def _point_blocked(origin: np.ndarray, px: float, py: float, owner: int, xy: np.ndarray, lwh: np.ndarray,
                   cos: np.ndarray, sin: np.ndarray, reach: np.ndarray, occlude: bool, boxes: np.ndarray,
                   box_cos: np.ndarray, box_sin: np.ndarray, box_reach: np.ndarray, starts: np.ndarray,
                   ends: np.ndarray, first: np.ndarray) -> bool:
    """Segment origin -> (px, py) meets a static box, another target's box (with ``occlude``) or a polygon;
    the boxes apart from the segment (``_apart``) are not tested."""
    for k in range(len(boxes)):
        if (not _apart(origin, px, py, boxes[k, 0], boxes[k, 1], box_reach[k])
                and _hits_box(origin, px, py, boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3], box_cos[k],
                              box_sin[k])):
            return True
    if occlude:
        for j in range(len(xy)):
            if (j != owner and not _apart(origin, px, py, xy[j, 0], xy[j, 1], reach[j])
                    and _hits_box(origin, px, py, xy[j, 0], xy[j, 1], lwh[j, 0], lwh[j, 1], cos[j], sin[j])):
                return True
    for p in range(len(first)):
        if _hits_polygon(origin, px, py, starts, ends, first[p], first[p + 1] if p + 1 < len(first) else len(starts)):
            return True
    return False


@helper
def _hits_box(a: np.ndarray, bx: float, by: float, x: float, y: float, length: float, width: float, c: float,
              s: float) -> bool:
    """Segment a -> b meets box [x, y, length, width, yaw] (c, s = cos, sin yaw): ``segments_hit_boxes``' slab
    test with its operations (R^T v = (c v_x + s v_y, -s v_x + c v_y); np.minimum / np.maximum keep its NaN
    handling)."""
    acx, acy, bax, bay = a[0] - x, a[1] - y, bx - a[0], by - a[1]
    hx, hy = length / 2.0, width / 2.0
    q0x, q0y = c * acx + s * acy, -s * acx + c * acy  # R^T (a - c)
    dx, dy = c * bax + s * bay, -s * bax + c * bay  # R^T (b - a)
    t1x, t2x, t1y, t2y = (-hx - q0x) / dx, (hx - q0x) / dx, (-hy - q0y) / dy, (hy - q0y) / dy
    enter = np.maximum(np.minimum(t1x, t2x), np.minimum(t1y, t2y))
    leave = np.minimum(np.maximum(t1x, t2x), np.maximum(t1y, t2y))
    return np.maximum(enter, 0.0) <= np.minimum(leave, 1.0)


@helper
def _cross_z(ox: float, oy: float, px: float, py: float, qx: float, qy: float) -> float:
    """z of (p - o) x (q - o)."""
    return (px - ox) * (qy - oy) - (py - oy) * (qx - ox)


@helper
def _hits_polygon(a: np.ndarray, bx: float, by: float, starts: np.ndarray, ends: np.ndarray, lo: int, hi: int) -> bool:
    """Segment a -> b meets the polygon of edges lo .. hi - 1: ``segments_hit_polygons``' tests (crosses an
    edge, or b inside by the crossing number of the ray from b towards +x)."""
    inside = False
    for e in range(lo, hi):
        cx, cy, dx, dy = starts[e, 0], starts[e, 1], ends[e, 0], ends[e, 1]
        if (_cross_z(a[0], a[1], bx, by, cx, cy) * _cross_z(a[0], a[1], bx, by, dx, dy) <= 0
                and _cross_z(cx, cy, dx, dy, a[0], a[1]) * _cross_z(cx, cy, dx, dy, bx, by) <= 0):
            return True
        if (cy > by) != (dy > by) and bx < cx + (by - cy) * (dx - cx) / (dy - cy):
            inside = not inside
    return inside
