"""Image-box tracker (Maqsud's ROIF thesis Sec. 4.7): IoU-cost Hungarian association and a constant-velocity
Kalman filter on box centre and size, SORT-like. Boxes are (N, 4) [x1, y1, x2, y2] px.

State x = [cx, cy, w, h, vcx, vcy, vw, vh] (px, px/s), measurement z = [cx, cy, w, h]:
  predict  x' = F x, P' = F P F^T + Q,  F = [[I4, dt I4], [0, I4]],
           Q per coordinate = sigma_a^2 g g^T, g = [dt^2/2, dt] (white-noise acceleration)
  update   y = z - H x, S = H P H^T + R, K = P H^T S^-1, x+ = x + K y,
           P+ = (I - K H) P (I - K H)^T + K R K^T  (Joseph form, as filterpy's KalmanFilter),
  H = [I4 0], R = sigma_z^2 I4. The filters of all tracks run batched; ``tests/unit/test_roif.py``
  checks them against filterpy step by step.

Association (Sec. 4.7.2): cost C(i, j) = 1 - IoU(D_i, T_j) (eq. 5.1-5.5) between detections and
predicted track boxes; pairs need IoU >= ``iou_gate``; minimum total cost one-to-one
(``v2i.fusion.association.assign``, the shortest augmenting path solver of ``v2i.fusion.lsap``).

Track management (Sec. 4.7.3): an unmatched detection starts a tentative track (velocity 0,
``init_velocity_std_pxps``); ``confirm_hits`` hits confirm it; a tentative track is deleted at its
first miss, a confirmed one after more than ``max_misses`` consecutive misses (it coasts,
predicted only, until then). Ids are unique within an instance, from 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from v2i.fusion.association import assign
from v2i.fusion.roif import iou_matrix

DIM_X, DIM_Z = 8, 4
H_BOX = np.hstack([np.eye(DIM_Z), np.zeros((DIM_Z, DIM_Z))])  # z = H x


@dataclass(frozen=True)
class BoxTrackerConfig:
    iou_gate: float = 0.1  # least IoU of a (detection, predicted track) pair
    confirm_hits: int = 2  # hits that confirm a track
    max_misses: int = 3  # consecutive misses a confirmed track survives (coasting)
    measurement_std_px: float = 4.0  # sigma_z of centre and size
    accel_std_pxps2: float = 60.0  # sigma_a, white-noise acceleration of each coordinate
    init_velocity_std_pxps: float = 100.0  # prior std of a new track's rates


def transition(dt_s: float) -> np.ndarray:
    """F (8, 8) = [[I4, dt I4], [0, I4]]."""
    f = np.eye(DIM_X)
    f[:DIM_Z, DIM_Z:] = dt_s * np.eye(DIM_Z)
    return f


def process_noise(dt_s: float, accel_std: float) -> np.ndarray:
    """Q (8, 8): per coordinate sigma_a^2 g g^T, g = [dt^2/2, dt] (position, rate)."""
    g = np.array([0.5 * dt_s**2, dt_s])
    block = accel_std**2 * np.outer(g, g)
    q = np.zeros((DIM_X, DIM_X))
    for i in range(DIM_Z):
        q[np.ix_([i, i + DIM_Z], [i, i + DIM_Z])] = block
    return q


def kf_predict(x: np.ndarray, p: np.ndarray, dt_s: float, accel_std: float) -> tuple[np.ndarray, np.ndarray]:
    """Batched predict: x (T, 8), P (T, 8, 8) -> F x, F P F^T + Q."""
    f = transition(dt_s)
    return x @ f.T, f @ p @ f.T + process_noise(dt_s, accel_std)


def kf_update(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched update of x (T, 8), P (T, 8, 8) with z (T, 4), R (4, 4); Joseph form."""
    s = H_BOX @ p @ H_BOX.T + r  # S = H P H^T + R, (T, 4, 4)
    k = p @ H_BOX.T @ np.linalg.inv(s)  # K = P H^T S^-1, (T, 8, 4)
    y = z - x @ H_BOX.T
    x_new = x + np.einsum("tij,tj->ti", k, y)
    i_kh = np.eye(DIM_X) - k @ H_BOX
    p_new = i_kh @ p @ np.swapaxes(i_kh, 1, 2) + k @ r @ np.swapaxes(k, 1, 2)
    return x_new, p_new


def xyxy_to_z(xyxy: np.ndarray) -> np.ndarray:
    """Boxes (N, 4) [x1, y1, x2, y2] -> (N, 4) [cx, cy, w, h]."""
    b = np.asarray(xyxy, float).reshape(-1, 4)
    return np.column_stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2, b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]])


def z_to_xyxy(z: np.ndarray) -> np.ndarray:
    """(N, 4+) [cx, cy, w, h, ...] -> boxes (N, 4) [x1, y1, x2, y2]."""
    z = np.atleast_2d(np.asarray(z, float))
    half = np.abs(z[:, 2:4]) / 2
    return np.column_stack([z[:, 0] - half[:, 0], z[:, 1] - half[:, 1], z[:, 0] + half[:, 0], z[:, 1] + half[:, 1]])


@dataclass(frozen=True)
class BoxTracks:
    """Confirmed tracks after a step: ids (K,), xyxy (K, 4) px, scores (K,), cls (K,), detection (K,):
    the detection row that updated it this step (-1: coasting)."""

    ids: np.ndarray
    xyxy: np.ndarray
    scores: np.ndarray
    cls: np.ndarray
    detection: np.ndarray


class BoxTracker:
    """Tracks of image boxes; ``step(xyxy, scores, cls, t_s)`` once per frame, times increasing."""

    def __init__(self, config: BoxTrackerConfig = BoxTrackerConfig()):
        self.config = config
        self.x, self.p = np.zeros((0, DIM_X)), np.zeros((0, DIM_X, DIM_X))
        self.ids = np.zeros(0, np.int64)
        self.hits, self.misses = np.zeros(0, int), np.zeros(0, int)
        self.scores, self.cls = np.zeros(0), np.zeros(0, np.int64)
        self._next_id, self._t_s = 1, None

    def step(self, xyxy: np.ndarray, scores: np.ndarray, cls: np.ndarray, t_s: float) -> BoxTracks:
        """Predict to t_s, associate, update, start and delete tracks; the confirmed tracks."""
        c = self.config
        if self._t_s is not None and len(self.x):
            self.x, self.p = kf_predict(self.x, self.p, t_s - self._t_s, c.accel_std_pxps2)
        self._t_s = t_s
        xyxy = np.asarray(xyxy, float).reshape(-1, 4)
        pairs = assign(1.0 - iou_matrix(xyxy, z_to_xyxy(self.x)), gate=1.0 - c.iou_gate)
        det, trk = pairs.matches[:, 0], pairs.matches[:, 1]
        r = c.measurement_std_px**2 * np.eye(DIM_Z)
        if len(trk):
            self.x[trk], self.p[trk] = kf_update(self.x[trk], self.p[trk], xyxy_to_z(xyxy[det]), r)
        self.hits[trk] += 1
        self.misses[trk] = 0
        self.misses[pairs.unmatched_b] += 1
        self.scores[trk], self.cls[trk] = np.asarray(scores, float)[det], np.asarray(cls, np.int64)[det]
        detection = np.full(len(self.x), -1)
        detection[trk] = det
        confirmed = self.hits >= c.confirm_hits
        keep = np.where(confirmed, self.misses <= c.max_misses, self.misses == 0)
        self._select(keep)
        detection = detection[keep]
        self._start(xyxy[pairs.unmatched_a], np.asarray(scores, float)[pairs.unmatched_a],
                    np.asarray(cls, np.int64)[pairs.unmatched_a])
        detection = np.concatenate([detection, pairs.unmatched_a])
        out = self.hits >= c.confirm_hits
        return BoxTracks(self.ids[out].copy(), z_to_xyxy(self.x[out]), self.scores[out].copy(),
                         self.cls[out].copy(), detection[out])

    def _select(self, keep: np.ndarray) -> None:
        self.x, self.p, self.ids = self.x[keep], self.p[keep], self.ids[keep]
        self.hits, self.misses, self.scores, self.cls = self.hits[keep], self.misses[keep], self.scores[keep], self.cls[keep]

    def _start(self, xyxy: np.ndarray, scores: np.ndarray, cls: np.ndarray) -> None:
        """New tentative tracks at the boxes (N, 4): rates 0 with ``init_velocity_std_pxps``."""
        n, c = len(xyxy), self.config
        x0 = np.hstack([xyxy_to_z(xyxy), np.zeros((n, DIM_Z))])
        p0 = np.diag([c.measurement_std_px**2] * DIM_Z + [c.init_velocity_std_pxps**2] * DIM_Z)
        self.x = np.vstack([self.x, x0])
        self.p = np.concatenate([self.p, np.broadcast_to(p0, (n, DIM_X, DIM_X))])
        self.ids = np.concatenate([self.ids, np.arange(self._next_id, self._next_id + n)])
        self._next_id += n
        self.hits = np.concatenate([self.hits, np.ones(n, int)])
        self.misses = np.concatenate([self.misses, np.zeros(n, int)])
        self.scores, self.cls = np.concatenate([self.scores, scores]), np.concatenate([self.cls, cls])
