"""Kinematic prediction of object sets with explicit time steps."""

from __future__ import annotations

import numpy as np

from v2i.core.objects import ObjectArray


def predict_cv(objs: ObjectArray, dt_s) -> ObjectArray:
    """Constant velocity: p(t + dt) = p + v dt. ``dt_s`` scalar or (N,) seconds.

    Position covariance grows by the velocity uncertainty we do not carry; callers
    that need honest covariances use a Kalman filter instead.
    """
    dt = np.broadcast_to(np.asarray(dt_s, dtype=float), (len(objs),))
    return objs.with_(xy=objs.xy + objs.vxy * dt[:, None], age_s=objs.age_s + np.maximum(dt, 0.0))


def predict_ca(objs: ObjectArray, dt_s) -> ObjectArray:
    """Constant acceleration: p += v dt + a dt^2 / 2, v += a dt. ``dt_s`` scalar or (N,) seconds."""
    if isinstance(dt_s, (float, int)):  # one step for all: the broadcast column's sums, without broadcasting
        dt, zero = np.float64(dt_s), np.float64(0.0)  # numpy scalars: float64 results, as with a float64 column
        xy, vxy = ca_step(objs.xy, objs.vxy, objs.axy, dt)
        return objs.with_(xy=xy, vxy=vxy, age_s=objs.age_s + max(dt, zero))  # np.maximum(dt, 0): dt unless 0 > dt
    dt = np.broadcast_to(np.asarray(dt_s, dtype=float), (len(objs),))[:, None]  # (NaN and -0.0 stay)
    xy, vxy = ca_step(objs.xy, objs.vxy, objs.axy, dt)
    return objs.with_(xy=xy, vxy=vxy, age_s=objs.age_s + np.maximum(dt[:, 0], 0.0))


def ca_step(xy: np.ndarray, vxy: np.ndarray, axy: np.ndarray, dt) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 2) m and velocities (N, 2) m/s after dt at constant acceleration:
    p + v dt + a dt^2 / 2 and v + a dt, for dt a float64 scalar or an (N, 1) column of seconds
    (dt^2 of a float64 column, numpy's square, is dt * dt: the same bits either way)."""
    return xy + vxy * dt + 0.5 * axy * (dt * dt), vxy + axy * dt


def trajectories_cv(objs: ObjectArray, horizon_s: float, step_s: float) -> np.ndarray:
    """(N, K, 3) [x, y, yaw] at t + k step_s, k = 1..K, K = round(horizon / step), at constant velocity.

    The heading is the velocity's direction, or the object's yaw when it stands (< 0.5 m/s).
    """
    k = np.arange(1, round(horizon_s / step_s) + 1) * step_s  # (K,)
    xy = objs.xy[:, None, :] + objs.vxy[:, None, :] * k[None, :, None]  # (N, K, 2)
    moving = np.linalg.norm(objs.vxy, axis=1) >= 0.5
    yaw = np.where(moving, np.arctan2(objs.vxy[:, 1], objs.vxy[:, 0]), objs.yaw)  # (N,)
    return np.concatenate([xy, np.broadcast_to(yaw[:, None, None], (len(objs), len(k), 1))], axis=2)
