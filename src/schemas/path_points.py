"""Fast validation of a predicted path's point tuples (``PredictedPath.x`` / ``y`` / ``yaw``).

Per point, the models check a float's range and quantise it in Python (``quantize.quantize``,
the yaw's wrap and grid): ~2 us a point, and a dense RSU list carries ~40 paths x 3 x 60
points per message (both at the RSU that builds it and at each OBU that decodes it). Here a
tuple of plain floats inside the range is checked and quantised as one array with the same
IEEE operations, so the values are bit for bit those of the per-point path:

    k = rint(v / step) + 0.0   (round half to even, as Python's ``round``; + 0.0 turns -0 into 0)
    v' = k * step
    yaw: w = (v + pi) mod 2 pi - pi (``numpy.remainder`` is Python's float ``%``);
         k = rint(w / step_yaw); k -= 3600 where k >= 1800; v' = k * step_yaw

Anything else (another type, a value out of range or NaN, too many points) goes to pydantic's
own validation, so accepted values and error messages are exactly the models'.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from pydantic import ValidatorFunctionWrapHandler, WrapValidator

from schemas import quantize as q

_FLOAT_ONLY = frozenset({float})


def grid_positions(values: np.ndarray) -> np.ndarray:
    """``quantize.quantize(v, POSITION_M)`` of each value; values (K,) -> (K,)."""
    return (np.rint(values / q.POSITION_M) + 0.0) * q.POSITION_M


def grid_yaws(values: np.ndarray) -> np.ndarray:
    """``object_state._yaw(v)`` of each value: wrapped to [-pi, pi) on the 0.1 deg grid; (K,) -> (K,)."""
    wrapped = np.remainder(values + math.pi, 2.0 * math.pi) - math.pi
    k = np.rint(wrapped / q.YAW_RAD) + 0.0
    return np.where(k >= 1800, k - 3600, k) * q.YAW_RAD


def points_validator(low: float, high: float, max_points: int,
                     grid: Callable[[np.ndarray], np.ndarray]) -> WrapValidator:
    """A ``WrapValidator`` for ``tuple[float-with-range-and-grid, ...]`` of at most ``max_points``:
    a list or tuple of plain floats in [low, high] is gridded as an array; anything else is
    handed to the field's own validation."""

    def validate(value: Any, handler: ValidatorFunctionWrapHandler) -> tuple[float, ...]:
        if type(value) in (list, tuple) and len(value) <= max_points and set(map(type, value)) <= _FLOAT_ONLY:
            points = np.array(value, dtype=np.float64)
            if bool(np.all((points >= low) & (points <= high))):  # NaN fails both
                return tuple(grid(points).tolist())
        return handler(value)

    return WrapValidator(validate)


_PATH_KEYS = frozenset({"id", "x", "y", "yaw"})
_ID_END = 2**32


def _gridded(points: np.ndarray, m: int, position_max_m: float, yaw_max: float) -> np.ndarray | None:
    """points (3 M,) [x of every point, then y, then yaw] gridded (positions on the first 2 M,
    yaws on the last M), or None when a value is out of range or NaN. Element-wise operations
    only: each value is gridded exactly as alone (``grid_positions`` / ``grid_yaws``)."""
    xy, yaw = points[:2 * m], points[2 * m:]
    if not (bool(np.all(np.abs(xy) <= position_max_m)) and bool(np.all(np.abs(yaw) <= yaw_max))):
        return None
    out = np.empty_like(points)
    out[:2 * m], out[2 * m:] = grid_positions(xy), grid_yaws(yaw)
    return out


def _split(gridded: np.ndarray, lengths: list[int]) -> tuple[list[tuple], list[tuple], list[tuple]]:
    """Per-path x, y, yaw tuples of ``gridded`` (3 M,) [x..., y..., yaw...] for paths of ``lengths``
    (N,), M = sum(lengths): one (3 N, K) ``tolist`` when every path has the same length K."""
    n = len(lengths)
    if n and lengths.count(lengths[0]) == n:
        rows = list(map(tuple, gridded.reshape(3 * n, lengths[0]).tolist()))
        return rows[:n], rows[n:2 * n], rows[2 * n:]
    flat, m = gridded.tolist(), len(gridded) // 3
    ends = np.cumsum(lengths, dtype=np.int64).tolist()
    spans = list(zip([0, *ends[:-1]], ends))
    xs, ys, yaws = ([tuple(flat[c * m + a:c * m + b]) for a, b in spans] for c in range(3))
    return xs, ys, yaws


def paths_from_dicts(value: Any, max_paths: int, max_points: int, position_max_m: float,
                     yaw_max: float) -> list[tuple[int, tuple, tuple, tuple]] | None:
    """(id, x, y, yaw) per path of a list of ``{"id", "x", "y", "yaw"}`` dicts (a decoded
    ``PredictionList.paths``) whose ids are plain ints in [0, 2^32) and points plain floats in
    range, equal lengths of at most ``max_points``: all points checked and gridded in one pass.
    None for anything else (the models then validate it and name the problem)."""
    if type(value) not in (list, tuple) or len(value) > max_paths:
        return None
    ids, lengths, xs, ys, yaws = [], [], [], [], []
    for item in value:
        if type(item) is not dict or item.keys() != _PATH_KEYS:
            return None
        i, x, y, yaw = item["id"], item["x"], item["y"], item["yaw"]
        if type(i) is not int or not 0 <= i < _ID_END or type(x) not in (list, tuple):
            return None
        if type(y) not in (list, tuple) or type(yaw) not in (list, tuple) or not len(x) == len(y) == len(yaw) <= max_points:
            return None
        ids.append(i)
        lengths.append(len(x))
        xs.extend(x)
        ys.extend(y)
        yaws.extend(yaw)
    points = xs + ys + yaws  # (3 M,): every path's x, then y, then yaw
    if not set(map(type, points)) <= _FLOAT_ONLY:
        return None
    gridded = _gridded(np.array(points, dtype=np.float64), len(xs), position_max_m, yaw_max)
    if gridded is None:
        return None
    return list(zip(ids, *_split(gridded, lengths)))


def paths_from_array(ids: np.ndarray, points: np.ndarray, max_points: int, position_max_m: float,
                     yaw_max: float) -> list[tuple[int, tuple, tuple, tuple]] | None:
    """(id, x, y, yaw) per path of ids (N,) and points (N, K, 3) [x, y, yaw], gridded in one
    pass; None when an id or a value is out of range or K > max_points (the models then name it)."""
    ids, points = np.asarray(ids), np.asarray(points, dtype=np.float64)
    if ids.ndim != 1 or points.ndim != 3 or points.shape[0] != len(ids) or points.shape[2] != 3 or points.shape[1] > max_points:
        return None
    if len(ids) and not (bool(np.all(ids >= 0)) and bool(np.all(ids < _ID_END))):
        return None
    n, k = points.shape[:2]
    gridded = _gridded(np.moveaxis(points, 2, 0).reshape(-1), n * k, position_max_m, yaw_max)  # (3 N K,)
    if gridded is None:
        return None
    return list(zip(ids.tolist(), *_split(gridded, [k] * n)))
