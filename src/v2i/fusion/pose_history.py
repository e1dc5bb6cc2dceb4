"""Time-indexed ego poses, so data can be paired with the pose at its own time.

Pose uncertainty between two stored poses is interpolated linearly too:
cov(a) = (1 - a) cov_p + a cov_q. The interpolated error (1 - a) e_p + a e_q has covariance
(1 - a)^2 cov_p + a^2 cov_q + a (1 - a) (C_pq + C_qp), which is at most the linear blend
whatever the correlation C_pq (per direction u: sigma(a)^2 <= ((1 - a) sigma_p + a sigma_q)^2
<= (1 - a) sigma_p^2 + a sigma_q^2, Cauchy-Schwarz then convexity), and equals it when the
two errors are the same (Gauss-Markov errors 0.1 s apart with tau = 5 s nearly are). Extrapolated
poses keep the uncertainty of the pose they start from (the velocity is taken as exact).
"""

from __future__ import annotations

import bisect
import math
from collections import deque

from v2i.core.frames import Pose2D, PoseUncertainty

_TWO_PI = 2.0 * math.pi


class PoseHistory:
    """Poses sorted by time (ns, one clock); keeps ``horizon_s`` of history."""

    def __init__(self, horizon_s: float = 5.0):
        self._horizon_ns = int(horizon_s * 1e9)
        self._t: deque[int] = deque()
        self._poses: deque[Pose2D] = deque()

    def __len__(self) -> int:
        return len(self._t)

    def add(self, t_ns: int, pose: Pose2D) -> None:
        """Insert a pose; out-of-order poses are placed where they belong."""
        i = bisect.bisect_right(self._t, t_ns)
        self._t.insert(i, t_ns)
        self._poses.insert(i, pose)
        while self._t and self._t[-1] - self._t[0] > self._horizon_ns:
            self._t.popleft()
            self._poses.popleft()

    def at(self, t_ns: int, uncertainty: bool = True) -> Pose2D | None:
        """Pose at t_ns: linear interpolation between neighbours, constant-velocity
        extrapolation outside the stored span; None when empty. ``uncertainty=False``: where the
        ego is, without its error statistics (an interpolated pose's ``uncertainty`` is then None)."""
        if not self._t:
            return None
        i = bisect.bisect_left(self._t, t_ns)
        if i == 0 or i == len(self._t):
            j = 0 if i == 0 else len(self._t) - 1
            return _extrapolate(self._poses[j], (t_ns - self._t[j]) * 1e-9)
        t0, t1 = self._t[i - 1], self._t[i]
        a = (t_ns - t0) / (t1 - t0) if t1 > t0 else 0.0
        return _interpolate(self._poses[i - 1], self._poses[i], a, uncertainty)


def _wrap(rad: float) -> float:
    """``v2i.core.frames.wrap_angle`` of one Python float, to [-pi, pi): the same IEEE operations (a float's
    ``%`` is numpy's remainder: fmod, then the divisor's sign), without the 0-d arrays."""
    return (rad + math.pi) % _TWO_PI - math.pi


def _interpolate(p: Pose2D, q: Pose2D, a: float, uncertainty: bool = True) -> Pose2D:
    # yaw along the shorter arc: yaw = p + a * wrap(q - p)
    yaw = _wrap(float(p.yaw) + a * _wrap(float(q.yaw) - float(p.yaw)))
    lerp = lambda u, v: (1 - a) * u + a * v  # noqa: E731
    return Pose2D(lerp(p.x, q.x), lerp(p.y, q.y), yaw, lerp(p.vx, q.vx), lerp(p.vy, q.vy),
                  _interpolate_uncertainty(p.uncertainty, q.uncertainty, a) if uncertainty else None)


def _interpolate_uncertainty(p: PoseUncertainty | None, q: PoseUncertainty | None, a: float) -> PoseUncertainty | None:
    """(1 - a) cov_p + a cov_q (module docstring); the nearer pose's alone when the other has none."""
    if p is None or q is None:
        return p if a < 0.5 else q
    tau_s = (1 - a) * p.correlation_time_s + a * q.correlation_time_s
    return PoseUncertainty.trusted((1 - a) * p.cov + a * q.cov, tau_s)


def _extrapolate(p: Pose2D, dt_s: float) -> Pose2D:
    return Pose2D(p.x + p.vx * dt_s, p.y + p.vy * dt_s, p.yaw, p.vx, p.vy, p.uncertainty)
