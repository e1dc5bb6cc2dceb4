"""Pinhole camera with radial distortion, posed in ``map`` (pure numpy + OpenCV).

Frames: ``map`` is x east, y north, z up (m). The camera frame is OpenCV's: x right, y down,
z along the optical axis. A map point X_w maps to the camera as X_c = R X_w + t, t = -R C
(C the camera centre), and to pixels as

    [u, v, 1]^T ~ K [x_c / z_c, y_c / z_c, 1]^T,  K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]

after OpenCV's distortion model (k1, k2, p1, p2, k3) on the normalised coordinates.
Points on the ground (z = 0) map to undistorted pixels by the homography
``H_ground = K [r1 r2 t]`` (r_i the columns of R), which the calibration (``v2i camera
calibrate``) estimates from surveyed points instead of knowing the pose.

Orientation from yaw (optical axis heading, CCW from +x), pitch (down positive) and roll:
the axis d = (cos p cos y, cos p sin y, -sin p); right r = (sin y, -cos y, 0) rolled about d;
down = d x r. R's rows are r, down, d.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from v2i.core.frames import Pose2D

from v2i.sim.scenario import RsuCameraConfig, VehicleCameraConfig


def rotation_from_angles(yaw_rad: float, pitch_rad: float, roll_rad: float = 0.0) -> np.ndarray:
    """World-to-camera rotation (3, 3) for an optical axis at yaw (CCW from +x), pitched down, rolled."""
    cy, sy, cp, sp = np.cos(yaw_rad), np.sin(yaw_rad), np.cos(pitch_rad), np.sin(pitch_rad)
    d = np.array([cp * cy, cp * sy, -sp])
    right = np.array([sy, -cy, 0.0])
    down = np.cross(d, right)
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)  # roll: rotate right/down about the axis
    right, down = cr * right + sr * down, -sr * right + cr * down
    return np.vstack([right, down, d])


def focal_from_hfov(width_px: int, hfov_deg: float) -> float:
    """f (px) = (W / 2) / tan(hfov / 2)."""
    return 0.5 * width_px / np.tan(np.deg2rad(hfov_deg) / 2.0)


@dataclass(frozen=True)
class PinholeCamera:
    """Intrinsics ``K`` (3, 3), distortion ``dist`` (5,), pose ``R`` (3, 3) and ``t`` (3,) map -> camera."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    @classmethod
    def from_pose(cls, position_m, yaw_rad: float, pitch_rad: float, width: int = 640, height: int = 384,
                  hfov_deg: float = 70.0, roll_rad: float = 0.0, dist=None) -> "PinholeCamera":
        """A camera at ``position_m`` (3,) in map with square pixels and the principal point centred."""
        f = focal_from_hfov(width, hfov_deg)
        K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
        R = rotation_from_angles(yaw_rad, pitch_rad, roll_rad)
        C = np.asarray(position_m, dtype=float)
        d = np.zeros(5) if dist is None else np.pad(np.asarray(dist, dtype=float), (0, 5 - len(dist)))
        return cls(K=K, R=R, t=-R @ C, width=int(width), height=int(height), dist=d)

    @classmethod
    def on_vehicle(cls, ego: Pose2D, mount_m, yaw_rad: float = 0.0, pitch_rad: float = 0.0, **kw) -> "PinholeCamera":
        """A camera on the vehicle: ``mount_m`` (3,) in base_link, looking ``yaw_rad`` off its heading."""
        c, s = np.cos(ego.yaw), np.sin(ego.yaw)
        x, y, z = mount_m
        position = (ego.x + c * x - s * y, ego.y + s * x + c * y, z)
        return cls.from_pose(position, ego.yaw + yaw_rad, pitch_rad, **kw)

    @property
    def centre(self) -> np.ndarray:
        """Camera centre C (3,) in map: C = -R^T t."""
        return -self.R.T @ self.t

    @property
    def distorted(self) -> bool:
        return bool(np.any(self.dist != 0.0))

    def turned(self, yaw_rad: float, pitch_rad: float, roll_rad: float) -> "PinholeCamera":
        """This camera rotated about its centre C by small angles in its own frame, signed as in
        ``from_pose``: pan (about the image's vertical axis y; yaw + d at zero pitch), tilt (about x;
        pitch + d) and roll (about the axis z; roll + d): R' = R_delta R, t' = -R' C."""
        r_delta, _ = cv2.Rodrigues(np.array([pitch_rad, yaw_rad, -roll_rad]))
        R = r_delta @ self.R
        return PinholeCamera(K=self.K, R=R, t=-R @ self.centre, width=self.width, height=self.height, dist=self.dist)

    def to_camera(self, points_m: np.ndarray) -> np.ndarray:
        """Map points (N, 3) -> camera frame (N, 3)."""
        return np.asarray(points_m, dtype=float).reshape(-1, 3) @ self.R.T + self.t

    def project(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map points (N, 3) -> pixels (N, 2) (distorted) and depth z_c (N,) m; z_c <= 0 is behind."""
        pc = self.to_camera(points_m)
        z = pc[:, 2]
        safe = np.where(z > 1e-6, z, 1e-6)
        if not self.distorted:
            uv = (pc[:, :2] / safe[:, None]) * self.K[0, 0] + self.K[:2, 2]
            return uv, z
        pts = np.column_stack([pc[:, :2] / safe[:, None], np.ones(len(pc))])
        uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist)
        return uv.reshape(-1, 2), z

    def ground_homography(self) -> np.ndarray:
        """H (3, 3): ground point [x, y, 1] (map, z = 0) -> undistorted pixel, H = K [r1 r2 t]."""
        return self.K @ np.column_stack([self.R[:, 0], self.R[:, 1], self.t])

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels (N, 2) -> ideal (undistorted) pixels (N, 2) of the same K."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        if not self.distorted or len(uv) == 0:
            return uv
        return cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, self.dist, P=self.K).reshape(-1, 2)


# Default wind sway of a camera on a traffic-signal pole (deg, std of each angle). A pole is a
# cantilever: a tip deflection delta of a pole of length L turns its top by 3 delta / (2 L);
# ~8 mm rms in a light wind on a 7 m pole gives 1.7 mrad = 0.1 deg, about one pixel of a
# 640 px, 70 deg camera. Assumed, not measured: vendors ship gyro image stabilisation because
# poles sway in wind and shake under passing trucks, and fixed coastal cameras drift by up to
# 10-30 px over months (Bergsma et al.'s Anglet cameras); each 0.1 deg of pitch moves a ground
# point dr = dpitch (r^2 + h^2) / h, 1.2 m at 70 m from a 7 m pole.
RSU_SWAY_DEG = 0.1
SWAY_MODES = 8  # sinusoids summed per angle


@dataclass(frozen=True)
class Sway:
    """A mount's wind sway: yaw, pitch and roll offsets (rad) as a seeded, stateless function of time.

    Each angle is a sum of ``SWAY_MODES`` sinusoids, a_k = sigma sqrt(2 / K),
    theta(t) = sum_k a_k cos(2 pi f_k t + phi_k), f_k = sway_hz U(0.7, 1.3), phi_k U(0, 2 pi):
    stationary with standard deviation sigma, its spectrum near the pole's first mode, and the
    same at a time whatever frames were rendered before. ``freq_hz``, ``phase_rad`` (3, K).
    """

    sigma_rad: float
    freq_hz: np.ndarray
    phase_rad: np.ndarray

    @classmethod
    def still(cls) -> "Sway":
        """No sway."""
        return cls(0.0, np.zeros((3, SWAY_MODES)), np.zeros((3, SWAY_MODES)))

    @classmethod
    def draw(cls, sigma_deg: float, sway_hz: float, rng: np.random.Generator) -> "Sway":
        shape = (3, SWAY_MODES)
        freq_hz = sway_hz * rng.uniform(0.7, 1.3, shape)
        return cls(float(np.deg2rad(sigma_deg)), freq_hz, rng.uniform(0, 2 * np.pi, shape))

    def angles_rad(self, t_s: float) -> np.ndarray:
        """(3,) yaw, pitch (down positive), roll offsets at ``t_s``."""
        a = self.sigma_rad * np.sqrt(2.0 / SWAY_MODES)
        return a * np.cos(2.0 * np.pi * self.freq_hz * t_s + self.phase_rad).sum(axis=1)

    def move(self, camera: PinholeCamera, t_s: float) -> PinholeCamera:
        """``camera`` turned about its centre by the sway at ``t_s`` (itself when sigma is 0)."""
        if self.sigma_rad == 0.0:
            return camera
        return camera.turned(*self.angles_rad(t_s))


def rsu_sway(cfg: RsuCameraConfig, rng: np.random.Generator) -> Sway:
    """The wind sway of a scenario's RSU camera (``cfg.image.sway_deg``, default ``RSU_SWAY_DEG``)."""
    im = cfg.image
    return Sway.draw(RSU_SWAY_DEG if im.sway_deg is None else im.sway_deg, im.sway_hz, rng)


def rsu_camera(cfg: RsuCameraConfig) -> PinholeCamera:
    """The rendered camera of a scenario's RSU: on its pole, angles from ``cfg.image`` or the RSU's.

    Auto pitch: the axis meets the ground 0.45 range_m out, pitch = atan(z / (0.45 range)).
    """
    im = cfg.image
    hfov = im.fov_deg if im.fov_deg is not None else cfg.fov_deg
    if hfov > 120.0:
        raise ValueError(f"RSU {cfg.id}: fov {hfov:g} deg is too wide for one pinhole camera; "
                         "set rsu.image.fov_deg (<= 120) and rsu.image.yaw_deg in the scenario")
    yaw = im.yaw_deg if im.yaw_deg is not None else cfg.yaw_deg
    p = cfg.position
    pitch = np.deg2rad(im.pitch_deg) if im.pitch_deg is not None else np.arctan2(p.z, 0.45 * cfg.range_m)
    return PinholeCamera.from_pose((p.x, p.y, p.z), np.deg2rad(yaw), pitch, im.width, im.height, hfov,
                                   dist=im.distortion)


def vehicle_camera(cfg: VehicleCameraConfig, ego: Pose2D) -> PinholeCamera:
    """The ego's on-board camera at the ego pose ``ego`` (map)."""
    im, m = cfg.image, cfg.mount
    return PinholeCamera.on_vehicle(ego, (m.x, m.y, m.z), np.deg2rad(im.yaw_deg or 0.0), np.deg2rad(im.pitch_deg or 0.0),
                                    width=im.width, height=im.height, hfov_deg=im.fov_deg or 90.0, dist=im.distortion)
