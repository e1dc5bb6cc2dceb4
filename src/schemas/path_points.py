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

from . import quantize as q

_FLOAT_ONLY = frozenset({float})


def grid_positions(values: np.ndarray) -> np.ndarray:
    """``quantize.quantize(v, POSITION_M)`` of each value; values (K,) -> (K,)."""
    return (np.rint(values / q.POSITION_M) + 0.0) * q.POSITION_M


def grid_yaws(values: np.ndarray) -> np.ndarray:
    """``messages._yaw(v)`` of each value: wrapped to [-pi, pi) on the 0.1 deg grid; (K,) -> (K,)."""
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
