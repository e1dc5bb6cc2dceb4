"""Localization's error steps in Python floats (sim.sensors.Localization) against the previous array
expressions, bit for bit: the same poses (x, y still numpy floats), the same draws."""

import math

import numpy as np

from fusion.frames import Pose2D, wrap_angle
from sim.scenario import LocalizationConfig
from sim.sensors import Localization


class _ArrayLocalization:
    """The previous code: the error as a (3,) array, yaw wrapped by fusion.frames.wrap_angle."""

    def __init__(self, cfg, rng):
        self.cfg, self.rng = cfg, rng
        self._sigma = np.array([cfg.x_std_m, cfg.y_std_m, cfg.yaw_std_rad])
        self._error, self._t_s = None, None

    def measure(self, true: Pose2D, t_s: float) -> Pose2D:
        w = self.rng.normal(0.0, 1.0, 3) * self._sigma
        tau = self.cfg.correlation_time_s
        if self._error is None or tau <= 0:
            self._error = w
        else:
            a = float(np.exp(-abs(t_s - self._t_s) / tau))
            self._error = a * self._error + np.sqrt(1.0 - a * a) * w
        self._t_s = t_s
        dx, dy, dyaw = self._error
        return Pose2D(x=true.x + dx, y=true.y + dy, yaw=float(wrap_angle(true.yaw + dyaw)), vx=true.vx, vy=true.vy)


class _World:
    def __init__(self, poses):
        self.poses = poses

    def ego_at(self, t_s):
        return self.poses[t_s]


def test_localization_equals_the_array_expressions():
    rng = np.random.default_rng(12)
    for tau in (0.0, 0.5, 3.0, 60.0):
        cfg = LocalizationConfig(x_std_m=0.3, y_std_m=0.2, yaw_std_rad=0.05, correlation_time_s=tau)
        times = np.cumsum(rng.uniform(0.01, 0.3, 300)).tolist()
        yaws = rng.choice([math.pi, -math.pi, 0.0, -0.0, 3.14159, -3.1416, 1e-17, 7.0, -40.0], 300)
        poses = {t: Pose2D(x=float(x), y=float(y), yaw=float(yaw), vx=1.0, vy=-0.5)
                 for t, x, y, yaw in zip(times, rng.normal(0, 100, 300), rng.normal(0, 100, 300),
                                         np.where(rng.random(300) < 0.5, yaws, rng.uniform(-4.0, 4.0, 300)))}
        new, old = Localization(cfg, np.random.default_rng(5)), _ArrayLocalization(cfg, np.random.default_rng(5))
        world = _World(poses)
        for t in times:
            got, want = new.measure(world, t), old.measure(poses[t], t)
            for name in ("x", "y", "yaw", "vx", "vy"):
                a, b = getattr(got, name), getattr(want, name)
                assert type(a) is type(b) and np.array([a]).tobytes() == np.array([b]).tobytes(), (name, a, b)


def test_float_wrap_equals_wrap_angle():
    rng = np.random.default_rng(13)
    values = np.concatenate([rng.uniform(-50.0, 50.0, 20000), np.arange(-20, 21) * math.pi,
                             [0.0, -0.0, 5e-324, -5e-324, 1e300, -1e300, np.nextafter(math.pi, 4.0),
                              np.nextafter(-math.pi, -4.0), np.nextafter(math.pi, 0.0)]])
    for v in values.tolist():
        got = (v + math.pi) % (2.0 * math.pi) - math.pi
        assert np.array([got]).tobytes() == np.array([float(wrap_angle(v))]).tobytes(), v
