"""Bird's-eye-view boxes: corners, polygons and rotated-box IoU (via shapely)."""

from __future__ import annotations

import math

import numpy as np
import shapely

from .objects import ObjectArray


def bev_boxes(objs: ObjectArray) -> np.ndarray:
    """(N, 5) boxes [x, y, length, width, yaw] of an object set."""
    return np.column_stack([objs.xy, objs.lwh[:, :2], objs.yaw]) if len(objs) else np.zeros((0, 5))


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """Corners (N, 4, 2), counter-clockwise, of boxes (N, 5) [x, y, l, w, yaw].

    corner = centre + R(yaw) [+-l/2, +-w/2]^T
    """
    boxes = np.asarray(boxes, dtype=float).reshape(-1, 5)
    half = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=float) * 0.5
    local = half[None, :, :] * boxes[:, None, 2:4]  # (N, 4, 2)
    c, s = np.cos(boxes[:, 4]), np.sin(boxes[:, 4])
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # (N, 2, 2)
    return np.einsum("nij,nkj->nki", rot, local) + boxes[:, None, :2]


def box_polygons(boxes: np.ndarray) -> np.ndarray:
    """Shapely polygons (N,) of boxes (N, 5)."""
    return shapely.polygons(box_corners(boxes))


def bev_iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU (N, M) of BEV boxes a (N, 5) and b (M, 5); IoU = |A n B| / |A u B|.

    Pairs whose centres are farther apart than the sum of their half diagonals cannot
    overlap and are skipped without a polygon intersection.
    """
    a, b = np.asarray(a, float).reshape(-1, 5), np.asarray(b, float).reshape(-1, 5)
    iou = np.zeros((len(a), len(b)))
    if not len(a) or not len(b):
        return iou
    reach = 0.5 * (np.hypot(a[:, 2], a[:, 3])[:, None] + np.hypot(b[:, 2], b[:, 3])[None, :])
    dist = np.linalg.norm(a[:, None, :2] - b[None, :, :2], axis=-1)
    ia, ib = np.nonzero(dist < reach)
    if len(ia):
        pa, pb = box_polygons(a)[ia], box_polygons(b)[ib]
        inter = shapely.area(shapely.intersection(pa, pb))
        union = a[ia, 2] * a[ia, 3] + b[ib, 2] * b[ib, 3] - inter
        iou[ia, ib] = np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)
    return iou


def bev_iou(a, b) -> float:
    """IoU of two BEV boxes [x, y, l, w, yaw]."""
    return float(bev_iou_matrix(np.asarray(a)[None], np.asarray(b)[None])[0, 0])


def bev_iou_pair(a: np.ndarray, b: np.ndarray) -> float:
    """``bev_iou_matrix(a[None], b[None])[0, 0]`` of two boxes a, b (5,), bit for bit: the same
    skip test (|c_a - c_b| = sqrt(dx^2 + dy^2) >= the half diagonals' sum: 0) and the same shapely
    intersection, both polygons from one ``box_polygons`` call, without the (N, M) bookkeeping."""
    boxes = np.vstack([a, b]).astype(float, copy=False)  # (2, 5)
    half_diagonal = np.hypot(boxes[:, 2], boxes[:, 3])
    ax, ay, al, aw, _ = boxes[0].tolist()
    bx, by, bl, bw, _ = boxes[1].tolist()
    dx, dy = ax - bx, ay - by
    if not math.sqrt(dx * dx + dy * dy) < 0.5 * float(half_diagonal[0] + half_diagonal[1]):  # NaN: skipped too
        return 0.0
    pa, pb = box_polygons(boxes)
    inter = float(shapely.area(shapely.intersection(pa, pb)))
    union = al * aw + bl * bw - inter
    return inter / max(union, 1e-12) if union > 0 else 0.0
