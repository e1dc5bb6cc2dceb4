"""2-D rigid frames (SE(2)) between ``map`` and ``base_link``, with the ego pose's uncertainty.

A pose (x, y, yaw) of frame B in frame A gives T_A<-B = [[R(yaw), t], [0, 1]].
Saravanan et al. eq. 3-4: T_Object2Base = T_Map2Base * T_Object2Map, with T_Map2Base the
inverse of the ego pose in map.

Pose uncertainty. The OBU knows an *estimate* of its pose, (t + dt, yaw + dyaw) with the
error e = (dt, dyaw) ~ N(0, Sigma) (Sigma 3x3 over x m, y m, yaw rad). A frame change with
that pose moves a point by the first-order error J e, so it adds J Sigma J^T to the point's
covariance. For p_m = R(yaw) p_b + t and d = p_m - t = R(yaw) p_b (the lever arm, map axes):

    dp_m/dt = I_2,   dp_m/dyaw = dR/dyaw p_b = S R p_b = S d = [-d_y, d_x],   S = R(pi/2)
    J_m = [I_2 | S d]                                                  (2x3, ``pose_jacobian``)

and for the inverse p_b = R(yaw)^T (p_m - t): dp_b/dt = -R^T, dp_b/dyaw = d(R^T)/dyaw d =
(S R)^T d = -R^T S d, so J_b = -R^T J_m and

    C_b = R^T C_m R + J_b Sigma J_b^T = R^T (C_m + J_m Sigma J_m^T) R
    C_m = R C_b R^T + J_m Sigma J_m^T

The yaw column grows with range: 0.005 rad at 300 m is 1.5 m. Velocities (over ground)
turn with the yaw only: v_b = R^T v_m, dv_b/dyaw = -R^T S v_m, so C_v gains
sigma_yaw^2 (S v)(S v)^T in map axes (positions and velocities share dyaw; the objects
carry no position-velocity cross covariance, so that correlation is dropped).

Which frame changes add it: one between the true ``map`` (where RSU objects live) and the
ego's ``base_link``. Own detections are measured in base_link; moved into map and back
with the same pose they come back exactly, so the OBU's map tracker lives in the map *as
its pose estimate places it* (map'), own detections enter it without pose covariance and
RSU objects with J_m Sigma J_m^T (``add_pose_uncertainty``), and its output goes back to
base_link without it. As the pose error drifts, map' moves between two estimates by the
error difference, of covariance ``PoseUncertainty.drift_cov``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from v2i.core.identity_memo import IdentityMemo
from v2i.core.objects import ObjectArray

_S = np.array([[0.0, -1.0], [1.0, 0.0]])  # R(pi/2): dR(yaw)/dyaw = S R(yaw)
_EYE2 = np.eye(2)


@dataclass(frozen=True, eq=False)
class PoseUncertainty:
    """Error statistics of an estimated pose.

    cov (3, 3): covariance of the error (x m, y m, yaw rad). correlation_time_s: tau of a
    first-order Gauss-Markov error, E[e(t) e(t + dt)^T] = exp(-|dt| / tau) cov (0: white,
    independent between poses; inf: one constant bias).
    """

    cov: np.ndarray
    correlation_time_s: float = 0.0

    def __post_init__(self) -> None:
        cov = np.array(self.cov, dtype=float)
        if cov.shape != (3, 3):
            raise ValueError(f"pose covariance must be 3x3 over (x, y, yaw), got shape {cov.shape}")
        if self.correlation_time_s < 0:
            raise ValueError(f"correlation_time_s must be >= 0, got {self.correlation_time_s}")
        cov.setflags(write=False)
        object.__setattr__(self, "cov", cov)

    @classmethod
    def trusted(cls, cov: np.ndarray, correlation_time_s: float) -> PoseUncertainty:
        """One made from a (3, 3) float64 array that nothing else holds and a tau >= 0 (a blend of two
        valid ones, ``v2i.fusion.pose_history``), without the checks and the copy: made read-only here."""
        cov.setflags(write=False)
        out = object.__new__(cls)
        object.__setattr__(out, "cov", cov)
        object.__setattr__(out, "correlation_time_s", correlation_time_s)
        return out

    @classmethod
    def from_stds(cls, x_std_m: float, y_std_m: float, yaw_std_rad: float,
                  correlation_time_s: float = 0.0) -> PoseUncertainty:
        return cls(np.diag([x_std_m**2, y_std_m**2, yaw_std_rad**2]), correlation_time_s)

    def drift_cov(self, dt_s: float) -> np.ndarray:
        """(3, 3) covariance of e(t + dt) - e(t): how far two estimates dt_s apart disagree.

        Cov(e1 - e0) = 2 cov - 2 exp(-|dt| / tau) cov = 2 (1 - exp(-|dt| / tau)) cov.
        """
        tau = self.correlation_time_s
        rho = 0.0 if tau <= 0 else math.exp(-abs(dt_s) / tau)
        return 2.0 * (1.0 - rho) * self.cov


@dataclass(frozen=True)
class Pose2D:
    """Pose of a body in ``map``: position (m), heading (rad, CCW from +x), velocity (m/s, map);
    ``uncertainty``: the error statistics of an estimated pose (None: exact, e.g. the truth)."""

    x: float
    y: float
    yaw: float
    vx: float = 0.0
    vy: float = 0.0
    uncertainty: PoseUncertainty | None = field(default=None, compare=False)


def wrap_angle(rad):
    """Wrap (array or scalar) to [-pi, pi)."""
    return (np.asarray(rad) + np.pi) % (2.0 * np.pi) - np.pi


def rotation(yaw: float) -> np.ndarray:
    """R(yaw), shape (2, 2)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


class _Axes:
    """What the frame changes of one ego pose share (read-only): rot = R(yaw) (2, 2), origin = t (2,) m and
    ``zero_offset()``, rot^T @ 0 (2,), the zero velocity offset as map_to_base's matrix product forms it (its
    zeros' signs), formed on first use."""

    __slots__ = ("rot", "origin", "_zero_offset")

    def __init__(self, ego: Pose2D):
        self.rot, self.origin = rotation(ego.yaw), np.array([ego.x, ego.y], dtype=float)
        self.rot.flags.writeable = self.origin.flags.writeable = False
        self._zero_offset: np.ndarray | None = None

    def zero_offset(self) -> np.ndarray:
        if self._zero_offset is None:
            self._zero_offset = self.rot.T @ np.zeros(2)
            self._zero_offset.flags.writeable = False
        return self._zero_offset


# a pose's axes, kept for the poses last asked about (a cycle changes frames with one ego pose several times)
_axes = IdentityMemo(_Axes, capacity=8)


def map_to_base_points(xy: np.ndarray, ego: Pose2D) -> np.ndarray:
    """Points (N, 2) in map -> base_link: p_b = R(yaw)^T (p_m - t)."""
    axes = _axes(ego)
    return (np.asarray(xy, dtype=float) - axes.origin) @ axes.rot


def outside_box_rows(xy: np.ndarray, ego: Pose2D, half_l_m: float, half_w_m: float) -> np.ndarray:
    """Indices (M,) of the points xy (N, 2) in map that lie outside the box |x_b| <= half_l_m,
    |y_b| <= half_w_m around the ego (p_b = ``map_to_base_points(xy, ego)``), ascending."""
    local = map_to_base_points(xy, ego)
    return np.flatnonzero(~((np.abs(local[:, 0]) <= half_l_m) & (np.abs(local[:, 1]) <= half_w_m)))


def base_to_map_points(xy: np.ndarray, ego: Pose2D) -> np.ndarray:
    """Points (N, 2) in base_link -> map: p_m = R(yaw) p_b + t."""
    axes = _axes(ego)
    return np.asarray(xy, dtype=float) @ axes.rot.T + axes.origin


def pose_jacobian(lever_xy_m: np.ndarray) -> np.ndarray:
    """J_m = dp_m / d(x, y, yaw) = [I_2 | S d], shape (N, 2, 3), for lever arms d (N, 2) m =
    p_m - t in map axes (see the module docstring)."""
    d = np.asarray(lever_xy_m, dtype=float).reshape(-1, 2)
    jac = np.empty((len(d), 2, 3))
    jac[:, :, :2] = _EYE2
    jac[:, :, 2] = d @ _S.T  # S d = [-d_y, d_x]
    return jac


def pose_cov_map(xy_m: np.ndarray, ego: Pose2D, cov: np.ndarray) -> np.ndarray:
    """J_m cov J_m^T, shape (N, 2, 2) m^2 in map axes: what a pose error of covariance cov
    (3, 3) adds to points xy_m (N, 2) in map, relative to the ego at (ego.x, ego.y)."""
    jac = pose_jacobian(np.asarray(xy_m, dtype=float) - _axes(ego).origin)
    return jac @ np.asarray(cov, dtype=float) @ jac.transpose(0, 2, 1)


def add_pose_uncertainty(objs: ObjectArray, ego: Pose2D, vel_offset: np.ndarray | None = None) -> ObjectArray:
    """Objects in map axes with the covariance of ego's pose error added (unchanged when the
    pose is exact): C += J_m Sigma J_m^T, C_v += sigma_yaw^2 (S v)(S v)^T with v = vxy - vel_offset.

    Also the change from the true map into the map as the ego's estimate places it (map').
    """
    if ego.uncertainty is None or not len(objs):
        return objs
    sigma = ego.uncertainty.cov
    sv = (objs.vxy - (0.0 if vel_offset is None else vel_offset)) @ _S.T  # (N, 2) S v
    return objs.with_(cov_xy=objs.cov_xy + pose_cov_map(objs.xy, ego, sigma),
                      cov_vxy=objs.cov_vxy + sigma[2, 2] * sv[:, :, None] * sv[:, None, :])


def _transform(objs: ObjectArray, rot: np.ndarray, xy: np.ndarray, dyaw: float,
               vel_offset: np.ndarray | None) -> ObjectArray:
    # velocities and covariances rotate with the frame: v' = R v - offset, C' = R C R^T; yaw wrapped to [-pi, pi)
    vxy = objs.vxy @ rot.T
    return objs.with_(
        xy=xy,
        yaw=(objs.yaw + dyaw + np.pi) % (2.0 * np.pi) - np.pi,
        vxy=vxy if vel_offset is None else vxy - vel_offset,
        axy=objs.axy @ rot.T,
        cov_xy=rot @ objs.cov_xy @ rot.T,
        cov_vxy=rot @ objs.cov_vxy @ rot.T,
    )


def map_to_base(objs: ObjectArray, ego: Pose2D, relative_velocity: bool = False,
                pose_uncertainty: bool = True) -> ObjectArray:
    """Objects in map -> base_link of ``ego``.

    Velocities stay absolute (over ground) unless ``relative_velocity``, which subtracts
    the ego velocity (expressed in base_link). With ``pose_uncertainty`` the covariances
    gain the ego pose's (C_b = R^T (C_m + J_m Sigma J_m^T) R); leave it off for objects
    already in the ego's own map' (its tracker's output).
    """
    axes = _axes(ego)
    rot = axes.rot.T
    ego_v_map = np.array([ego.vx, ego.vy]) if relative_velocity else None  # None: 0 (v - 0 is v, bit for bit)
    if pose_uncertainty:
        objs = add_pose_uncertainty(objs, ego, ego_v_map)
    xy = (np.asarray(objs.xy, dtype=float) - axes.origin) @ axes.rot  # map_to_base_points
    return _transform(objs, rot, xy, -ego.yaw, axes.zero_offset() if ego_v_map is None else rot @ ego_v_map)


def base_to_map(objs: ObjectArray, ego: Pose2D, pose_uncertainty: bool = True) -> ObjectArray:
    """Objects in base_link of ``ego`` -> map (velocities taken as over ground). With
    ``pose_uncertainty`` the covariances gain the ego pose's (C_m = R C_b R^T + J_m Sigma J_m^T);
    leave it off to enter the ego's own map', where its detections carry no pose error."""
    axes = _axes(ego)
    xy = np.asarray(objs.xy, dtype=float) @ axes.rot.T + axes.origin  # base_to_map_points
    out = _transform(objs, axes.rot, xy, ego.yaw, None)  # no offset: v - 0 is v, bit for bit
    return add_pose_uncertainty(out, ego) if pose_uncertainty else out
