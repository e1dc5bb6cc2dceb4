"""Sensor models observing a ``World``: on-board LiDAR detector, roadside camera, localisation.

Every model draws its noise from the injected ``numpy.random.Generator``; the same seed and
the same call sequence give identical outputs. Noise is drawn for every actor in a fixed
order before any selection, so one actor's visibility never shifts another actor's noise.
"""

from __future__ import annotations

import numpy as np

from v2i.core.clock import frame_times  # noqa: F401 (the sensors' capture times, imported from here too)
from v2i.core.frames import Pose2D, PoseUncertainty, base_to_map_points, map_to_base, wrap_angle
from v2i.core.objects import ObjectArray, diagonal_covariances
from schemas.classes import CLASS_DEFAULT_LWH, ObjectClass
from schemas.messages import UNKNOWN_VELOCITY_VAR

from v2i.sim.occlusion import visible_fraction
from v2i.sim.scenario import LidarConfig, LocalizationConfig, RsuCameraConfig
from v2i.sim.world import World

SOURCE_VEHICLE = 1
SOURCE_RSU = 2

_MIN_SIZE_M = 0.1


# row c = the prior size of class code c (the codes are 0 .. len - 1; a gap fails here, at import)
_DEFAULT_LWH_BY_CODE = np.array([CLASS_DEFAULT_LWH[ObjectClass(c)] for c in range(len(ObjectClass))], dtype=float)


def _default_lwh(cls: np.ndarray) -> np.ndarray:
    """Class prior sizes (N, 3) m for class codes (N,)."""
    return _DEFAULT_LWH_BY_CODE[np.asarray(cls, dtype=np.int64)].reshape(-1, 3)


def _confidence_clip(score: np.ndarray) -> np.ndarray:
    """``np.clip(score, 0.05, 1.0)`` bit for bit (NaN stays NaN), as two ufuncs without its wrappers."""
    return np.minimum(np.maximum(score, 0.05), 1.0)


class Lidar:
    """On-board LiDAR + CenterPoint-like detector: detections in the ego's true base_link."""

    def __init__(self, cfg: LidarConfig, rng: np.random.Generator):
        self.cfg = cfg
        self.rng = rng
        # (t_s, every actor's truth in the true base_link at t_s) of the last frame (scoring)
        self.last_truth: tuple[float, ObjectArray] | None = None
        self._mount = np.array([[cfg.mount.x, cfg.mount.y]])  # (1, 2) m in base_link
        self._mount.flags.writeable = False

    def origin(self, ego: Pose2D) -> np.ndarray:
        """Sensor position (2,) in map for the ego pose."""
        return base_to_map_points(self._mount, ego)[0]

    def visibility(self, world: World, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Per actor (N,): distance from the sensor (m) and visible fraction seen from it."""
        return self._visibility(world, world.actors_at(t_s), world.ego_at(t_s))

    def _visibility(self, world: World, gt: ObjectArray, ego: Pose2D,
                    wanted: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``visibility``; with ``wanted`` (N,) bool, the visible fraction of only those actors
        within range (0 for the rest, which still occlude)."""
        # occluders: buildings + every other actor's box (the ego carries the sensor)
        origin = self.origin(ego)
        dist = np.hypot(*(gt.xy - origin).T)
        sampled = None if wanted is None else wanted & (dist <= self.cfg.range_m)
        vis = visible_fraction(origin, gt, world.building_boxes, world.building_polygons, samples=9, sampled=sampled)
        return dist, vis

    def detect(self, world: World, t_s: float) -> ObjectArray:
        """Detections at capture time t_s (s) in the true base_link; ids -1, sources 1."""
        c, rng = self.cfg, self.rng
        ego, gt = world.ego_at(t_s), world.actors_at(t_s)
        n = len(gt)
        detected = rng.random(n) < c.detection_probability  # the first draw, as ever
        # only a detected actor in range can be kept: the others' visibility is never read
        dist, vis = self._visibility(world, gt, ego, wanted=detected)
        truth = map_to_base(gt, ego)  # over-ground velocity, rotated into base_link
        self.last_truth = (t_s, truth)
        xy = truth.xy + rng.normal(0.0, c.position_noise_std_m, (n, 2))
        z = truth.z + rng.normal(0.0, c.position_noise_std_m, n)
        yaw = wrap_angle(truth.yaw + rng.normal(0.0, c.yaw_noise_std_rad, n))
        lwh = np.maximum(truth.lwh + rng.normal(0.0, c.size_noise_std_m, (n, 3)), _MIN_SIZE_M)
        vxy = truth.vxy + rng.normal(0.0, c.velocity_noise_std_mps, (n, 2))
        # fewer returns on far or partly hidden objects -> lower score
        confidence = _confidence_clip(vis * (1.0 - 0.5 * dist / c.range_m))
        keep = (dist <= c.range_m) & (vis >= c.min_visible_fraction) & detected
        k = int(np.count_nonzero(keep))  # the kept rows alone
        return ObjectArray(
            ids=np.full(k, -1, dtype=np.int64), cls=truth.cls[keep], xy=xy[keep], z=z[keep], lwh=lwh[keep],
            yaw=yaw[keep], vxy=vxy[keep], cov_xy=diagonal_covariances(c.position_noise_std_m**2, k),
            confidence=confidence[keep], cov_vxy=diagonal_covariances(c.velocity_noise_std_mps**2, k),
            sources=np.full(k, SOURCE_VEHICLE, dtype=np.int64),
        )


def mean_error_at(range_m: np.ndarray, cfg: RsuCameraConfig) -> np.ndarray:
    """Mean Euclidean position error (N,) m of the camera at horizontal ranges (N,) m.

    Piecewise constant over the configured bands; beyond the last band, the last value.
    """
    return _band_values(range_m, *_error_bands(cfg))


def _error_bands(cfg: RsuCameraConfig) -> tuple[np.ndarray, np.ndarray]:
    """The camera's error bands: upper range edges (B,) m and mean errors (B,) m."""
    return np.array([b.max_range_m for b in cfg.position_error]), np.array([b.mean_error_m for b in cfg.position_error])


def _band_values(range_m: np.ndarray, edges: np.ndarray, means: np.ndarray) -> np.ndarray:
    """``mean_error_at`` from the bands (``_error_bands``)."""
    return means[np.minimum(np.searchsorted(edges, range_m, side="left"), len(means) - 1)]


def per_axis_sigma(mean_error_m: np.ndarray) -> np.ndarray:
    """Per-axis std (m) of an isotropic 2-D Gaussian error with the given mean Euclidean error.

    |e| of e ~ N(0, sigma^2 I_2) is Rayleigh with mean sigma sqrt(pi/2), so
    sigma = mean / sqrt(pi/2).
    """
    return np.asarray(mean_error_m, dtype=float) / np.sqrt(np.pi / 2.0)


class RsuCamera:
    """Roadside monocular camera + CAROM-like detector: detections in map, plus its delay."""

    def __init__(self, cfg: RsuCameraConfig, rng: np.random.Generator):
        self.cfg = cfg
        self.rng = rng
        self.last_visible_xy = np.zeros((0, 2))  # (T, 2) m: the truth the last frame could see (scoring)
        self._position = np.array([cfg.position.x, cfg.position.y])
        self._position.flags.writeable = False
        self._bands = _error_bands(cfg)
        self._yaw_rad, self._half_fov_rad = np.deg2rad(cfg.yaw_deg), np.deg2rad(cfg.fov_deg) / 2.0

    @property
    def position(self) -> np.ndarray:
        """The pole's position (2,) m in map (read-only)."""
        return self._position

    def coverage(self, world: World, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Per actor (N,): horizontal range from the pole (m) and whether it is observable.

        Observable = within range_m, inside the horizontal FOV, and not hidden by buildings.
        The camera looks down from the pole, so cars do not occlude each other.
        """
        return self._coverage(world, world.actors_at(t_s))

    def _coverage(self, world: World, gt: ObjectArray) -> tuple[np.ndarray, np.ndarray]:
        c = self.cfg
        rel = gt.xy - self.position
        rng_m = np.hypot(rel[:, 0], rel[:, 1])
        off_axis = wrap_angle(np.arctan2(rel[:, 1], rel[:, 0]) - self._yaw_rad)
        in_view = (rng_m <= c.range_m) & (np.abs(off_axis) <= self._half_fov_rad)
        vis = visible_fraction(self.position, gt, world.building_boxes, world.building_polygons, targets_occlude=False,
                               sampled=in_view)  # an actor out of view is not observable, however visible
        return rng_m, in_view & (vis >= c.min_visible_fraction)

    def detect(self, world: World, t_s: float) -> tuple[ObjectArray, float]:
        """Detections of the frame captured at t_s (s) in map (ids -1, sources 2, no velocity),
        and that frame's processing delay (s), uniform in processing_delay_ms."""
        c, rng = self.cfg, self.rng
        delay_s = rng.uniform(*c.processing_delay_ms) / 1000.0
        truth = world.actors_at(t_s)
        rng_m, observable = self._coverage(world, truth)
        self.last_visible_xy = truth.xy[observable]
        n = len(truth)
        sigma = per_axis_sigma(_band_values(rng_m, *self._bands))
        detected = rng.random(n) < c.detection_probability
        xy = truth.xy + rng.normal(0.0, 1.0, (n, 2)) * sigma[:, None]
        yaw = wrap_angle(truth.yaw + rng.normal(0.0, c.yaw_noise_std_rad, n))
        lwh = np.maximum(_default_lwh(truth.cls) + rng.normal(0.0, c.size_noise_std_m, (n, 3)), _MIN_SIZE_M)
        keep = observable & detected
        k, lwh, sigma = int(np.count_nonzero(keep)), lwh[keep], sigma[keep]  # the kept rows alone
        out = ObjectArray(
            ids=np.full(k, -1, dtype=np.int64), cls=truth.cls[keep], xy=xy[keep], z=lwh[:, 2] / 2.0, lwh=lwh,
            yaw=yaw[keep], vxy=np.zeros((k, 2)), cov_xy=sigma[:, None, None] ** 2 * np.eye(2),
            confidence=_confidence_clip(1.0 - 0.5 * rng_m[keep] / c.range_m),
            cov_vxy=diagonal_covariances(UNKNOWN_VELOCITY_VAR, k),  # ObjectArray's default: no velocity measured
            sources=np.full(k, SOURCE_RSU, dtype=np.int64),
        )
        return out, delay_s


class Localization:
    """Ego pose measurement: true pose + a slowly drifting Gaussian error on x, y, yaw.

    The error is a first-order Gauss-Markov process with stationary std sigma and
    correlation time tau: e_k = a e_{k-1} + sqrt(1 - a^2) sigma w_k, a = exp(-dt / tau)
    (e_0 = sigma w_0, so every e_k has covariance diag(sigma^2)). Each measured pose states
    these statistics (``uncertainty``), as a real localisation reports its covariance.
    """

    def __init__(self, cfg: LocalizationConfig, rng: np.random.Generator):
        self.cfg = cfg
        self.rng = rng
        self._sigma = np.array([cfg.x_std_m, cfg.y_std_m, cfg.yaw_std_rad])
        self.uncertainty = PoseUncertainty.from_stds(cfg.x_std_m, cfg.y_std_m, cfg.yaw_std_rad, cfg.correlation_time_s)
        self._error: np.ndarray | None = None
        self._t_s: float | None = None

    def _next_error(self, t_s: float) -> np.ndarray:
        w = self.rng.normal(0.0, 1.0, 3) * self._sigma
        tau = self.cfg.correlation_time_s
        if self._error is None or tau <= 0:
            self._error = w
        else:
            a = float(np.exp(-abs(t_s - self._t_s) / tau))
            self._error = a * self._error + np.sqrt(1.0 - a * a) * w
        self._t_s = t_s
        return self._error

    def measure(self, world: World, t_s: float) -> Pose2D:
        """Noisy ego pose in map at t_s (s) with its stated uncertainty; velocity passed through unchanged."""
        true = world.ego_at(t_s)
        dx, dy, dyaw = self._next_error(t_s)
        return Pose2D(x=true.x + dx, y=true.y + dy, yaw=float(wrap_angle(true.yaw + dyaw)), vx=true.vx, vy=true.vy,
                      uncertainty=self.uncertainty)
