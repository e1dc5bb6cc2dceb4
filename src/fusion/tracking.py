"""Multi-object tracker: constant-velocity Kalman filters, batched over tracks.

State per track x = [px, py, vx, vy] (map frame, m and m/s), covariance P (4, 4).
Predict: x' = F x, P' = F P F^T + Q with F = [[I, dt I], [0, I]] and Q the
discrete white-noise-acceleration model (sigma_a^2 [[dt^4/4 I, dt^3/2 I], [dt^3/2 I, dt^2 I]]).
Update with a position z (2,) and covariance R (2, 2): S = H P H^T + R, K = P H^T S^-1,
x += K (z - H x), P = (I - K H) P.

Life cycle: a new track is tentative; it is confirmed after ``confirm_hits`` updates;
a confirmed track not updated coasts (predicted only) and is deleted once its last
update is older than ``max_coast_s``; a tentative track is deleted at its first miss.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .association import assign, center_distance_cost
from .frames import wrap_angle
from .objects import ObjectArray

_H = np.hstack([np.eye(2), np.zeros((2, 2))])


@dataclass(frozen=True)
class TrackerConfig:
    gate_m: float = 5.0  # centre-distance gate for association
    accel_std_mps2: float = 3.0  # sigma_a of the process noise
    init_speed_std_mps: float = 10.0  # prior std of an unknown velocity
    confirm_hits: int = 2
    max_coast_s: float = 0.6


def cv_transition(dt_s: float, accel_std: float) -> tuple[np.ndarray, np.ndarray]:
    """F (4, 4) and Q (4, 4) of the constant-velocity model over dt_s seconds."""
    eye = np.eye(2)
    f = np.block([[eye, dt_s * eye], [np.zeros((2, 2)), eye]])
    q = accel_std**2 * np.block([[dt_s**4 / 4 * eye, dt_s**3 / 2 * eye], [dt_s**3 / 2 * eye, dt_s**2 * eye]])
    return f, q


class Tracker:
    """Tracks of one source; ids are unique within this instance, starting at 1."""

    def __init__(self, config: TrackerConfig = TrackerConfig()):
        self.config = config
        self._next_id = 1
        self._t_s: float | None = None
        self._x = np.zeros((0, 4))
        self._p = np.zeros((0, 4, 4))
        self._meta = ObjectArray.empty()  # ids, cls, z, lwh, yaw, confidence of each track
        self._hits = np.zeros(0, dtype=int)
        self._born_s = np.zeros(0)
        self._updated_s = np.zeros(0)

    def __len__(self) -> int:
        return len(self._x)

    def step(self, dets: ObjectArray, t_s: float) -> ObjectArray:
        """Predict every track to t_s, update with detections (map frame), return confirmed tracks."""
        self._predict(t_s)
        cost = center_distance_cost(self._x[:, :2], dets.xy, self._meta.cls, dets.cls)
        result = assign(cost, self.config.gate_m)
        self._update(result.matches, dets, t_s)
        self._prune(t_s)
        self._spawn(dets.take(result.unmatched_b), t_s)
        return self.confirmed(t_s)

    def confirmed(self, t_s: float) -> ObjectArray:
        keep = self._hits >= self.config.confirm_hits
        return self._as_objects(t_s).take(keep)

    def _predict(self, t_s: float) -> None:
        if self._t_s is not None and len(self._x):
            f, q = cv_transition(t_s - self._t_s, self.config.accel_std_mps2)
            self._x = self._x @ f.T
            self._p = f @ self._p @ f.T + q
        self._t_s = t_s

    def _update(self, matches: np.ndarray, dets: ObjectArray, t_s: float) -> None:
        if not len(matches):
            return
        ti, di = matches[:, 0], matches[:, 1]
        p = self._p[ti]
        s = p[:, :2, :2] + dets.cov_xy[di]  # S = H P H^T + R
        k = p[:, :, :2] @ np.linalg.inv(s)  # K = P H^T S^-1, (K, 4, 2)
        innov = dets.xy[di] - self._x[ti, :2]
        self._x[ti] += np.einsum("kij,kj->ki", k, innov)
        self._p[ti] = (np.eye(4) - k @ _H) @ p
        self._meta.lwh[ti] = dets.lwh[di]
        self._meta.z[ti] = dets.z[di]
        self._meta.yaw[ti] = wrap_angle(dets.yaw[di])
        self._meta.confidence[ti] = dets.confidence[di]
        self._hits[ti] += 1
        self._updated_s[ti] = t_s

    def _prune(self, t_s: float) -> None:
        stale = t_s - self._updated_s > self.config.max_coast_s
        tentative_miss = (self._hits < self.config.confirm_hits) & (self._updated_s < t_s)
        self._keep(~(stale | tentative_miss))

    def _keep(self, mask: np.ndarray) -> None:
        self._x, self._p, self._meta = self._x[mask], self._p[mask], self._meta.take(mask)
        self._hits, self._born_s, self._updated_s = self._hits[mask], self._born_s[mask], self._updated_s[mask]

    def _spawn(self, dets: ObjectArray, t_s: float) -> None:
        n = len(dets)
        if not n:
            return
        ids = np.arange(self._next_id, self._next_id + n)
        self._next_id += n
        x = np.column_stack([dets.xy, dets.vxy])
        p = np.zeros((n, 4, 4))
        p[:, :2, :2] = dets.cov_xy
        p[:, 2:, 2:] = np.eye(2) * self.config.init_speed_std_mps**2
        self._x, self._p = np.vstack([self._x, x]), np.concatenate([self._p, p])
        self._meta = ObjectArray.concat([self._meta, dets.with_(ids=ids)])
        self._hits = np.concatenate([self._hits, np.ones(n, dtype=int)])
        self._born_s = np.concatenate([self._born_s, np.full(n, t_s)])
        self._updated_s = np.concatenate([self._updated_s, np.full(n, t_s)])

    def _as_objects(self, t_s: float) -> ObjectArray:
        return self._meta.with_(
            xy=self._x[:, :2].copy(),
            vxy=self._x[:, 2:].copy(),
            axy=np.zeros((len(self), 2)),
            cov_xy=self._p[:, :2, :2].copy(),
            age_s=t_s - self._born_s,
        )
