"""Predicted path points gridded by the compiled loop (schemas.bit_rows.grid_path_points) against the
numpy expression (path_points.grid_positions / grid_yaws after the range test)."""

from __future__ import annotations

import math

import numpy as np

from fusion.jit import load_kernels
from schemas import path_points
from schemas import quantize as q
from schemas.bit_rows import grid_path_points
from schemas.limits import POSITION_MAX_M
from schemas.path_points import grid_positions, grid_yaws

YAW_MAX = 100.0


def _numpy(points: np.ndarray, m: int) -> np.ndarray | None:
    xy, yaw = points[:2 * m], points[2 * m:]
    if not (bool(np.all(np.abs(xy) <= POSITION_MAX_M)) and bool(np.all(np.abs(yaw) <= YAW_MAX))):
        return None
    return np.concatenate([grid_positions(xy), grid_yaws(yaw)])


def _compiled(points: np.ndarray, m: int) -> np.ndarray | None:
    out = np.empty_like(points)
    return out if grid_path_points(points, m, POSITION_MAX_M, YAW_MAX, q.POSITION_M, q.YAW_RAD, out) else None


def _edge_values(rng: np.random.Generator, size: int, yaws: bool = False) -> np.ndarray:
    """Positions and yaws at half steps, on the grid, around +-pi and the wrap, signed zeros, at the limits."""
    half = (rng.integers(-10**6, 10**6, size) + 0.5) * q.POSITION_M
    yaw_half = (rng.integers(-1900, 1900, size) + 0.5) * q.YAW_RAD
    near_pi = math.pi + rng.integers(-3, 4, size) * 1e-15 * rng.choice([-1.0, 1.0], size)
    pool = np.concatenate([yaw_half if yaws else half, yaw_half, near_pi, -near_pi,
                           [0.0, -0.0, math.pi, -math.pi, 2 * math.pi, 99.9999]])
    return rng.choice(pool, size)


def test_compiled_grid_equals_numpy_bit_for_bit():
    """Random, half-step, near-pi and signed-zero values, any M: the same bits or the same refusal
    (a value out of range or NaN anywhere)."""
    rng = np.random.default_rng(6)
    refused = passed = 0
    for trial in range(3000):
        m = int(rng.integers(0, 60))
        xy = np.where(rng.random(2 * m) < 0.5, rng.uniform(-2000.0, 2000.0, 2 * m), _edge_values(rng, 2 * m))
        yaw = np.where(rng.random(m) < 0.5, rng.uniform(-YAW_MAX, YAW_MAX, m), _edge_values(rng, m, yaws=True))
        points = np.concatenate([xy, yaw])
        if trial % 10 == 0 and len(points):  # out of range or NaN somewhere
            points[rng.integers(0, len(points))] = rng.choice([np.nan, POSITION_MAX_M * 1.01, -YAW_MAX * 1.5, np.inf])
        want, got = _numpy(points, m), _compiled(points, m)
        assert (want is None) == (got is None)
        if want is None:
            refused += 1
        else:
            assert got.tobytes() == want.tobytes()
            passed += 1
    assert refused > 200 and passed > 1500


def test_gridded_uses_the_compiled_loop_once_loaded():
    load_kernels()
    assert path_points._compiled_grid is not None
    points = np.array([1.005, -2.0, 3.14159, 0.5, -0.5, math.pi])
    assert path_points._gridded(points, 2, POSITION_MAX_M, YAW_MAX).tobytes() == _numpy(points, 2).tobytes()
