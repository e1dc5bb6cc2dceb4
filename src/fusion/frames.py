"""2-D rigid frames (SE(2)) between ``map`` and ``base_link``.

A pose (x, y, yaw) of frame B in frame A gives T_A<-B = [[R(yaw), t], [0, 1]].
Seed 000 eq. 3-4: T_Object2Base = T_Map2Base * T_Object2Map, with T_Map2Base the
inverse of the ego pose in map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .objects import ObjectArray


@dataclass(frozen=True)
class Pose2D:
    """Pose of a body in ``map``: position (m), heading (rad, CCW from +x), velocity (m/s, map)."""

    x: float
    y: float
    yaw: float
    vx: float = 0.0
    vy: float = 0.0


def wrap_angle(rad):
    """Wrap (array or scalar) to [-pi, pi)."""
    return (np.asarray(rad) + np.pi) % (2.0 * np.pi) - np.pi


def rotation(yaw: float) -> np.ndarray:
    """R(yaw), shape (2, 2)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


def map_to_base_points(xy: np.ndarray, ego: Pose2D) -> np.ndarray:
    """Points (N, 2) in map -> base_link: p_b = R(yaw)^T (p_m - t)."""
    return (np.asarray(xy, dtype=float) - [ego.x, ego.y]) @ rotation(ego.yaw)


def base_to_map_points(xy: np.ndarray, ego: Pose2D) -> np.ndarray:
    """Points (N, 2) in base_link -> map: p_m = R(yaw) p_b + t."""
    return np.asarray(xy, dtype=float) @ rotation(ego.yaw).T + [ego.x, ego.y]


def _transform(objs: ObjectArray, rot: np.ndarray, xy: np.ndarray, dyaw: float, vel_offset: np.ndarray) -> ObjectArray:
    # velocities and covariances rotate with the frame: v' = R v, C' = R C R^T
    return objs.with_(
        xy=xy,
        yaw=wrap_angle(objs.yaw + dyaw),
        vxy=objs.vxy @ rot.T - vel_offset,
        axy=objs.axy @ rot.T,
        cov_xy=rot @ objs.cov_xy @ rot.T,
        cov_vxy=rot @ objs.cov_vxy @ rot.T,
    )


def map_to_base(objs: ObjectArray, ego: Pose2D, relative_velocity: bool = False) -> ObjectArray:
    """Objects in map -> base_link of ``ego``.

    Velocities stay absolute (over ground) unless ``relative_velocity``, which subtracts
    the ego velocity (expressed in base_link).
    """
    rot = rotation(ego.yaw).T
    ego_v = rot @ [ego.vx, ego.vy] if relative_velocity else np.zeros(2)
    return _transform(objs, rot, map_to_base_points(objs.xy, ego), -ego.yaw, ego_v)


def base_to_map(objs: ObjectArray, ego: Pose2D) -> ObjectArray:
    """Objects in base_link of ``ego`` -> map (velocities taken as over ground)."""
    return _transform(objs, rotation(ego.yaw), base_to_map_points(objs.xy, ego), ego.yaw, np.zeros(2))
