"""Pixels to map: detector boxes through a calibrated ground homography (inverse perspective mapping).

A box's ground contact g is its bottom-centre pixel (Saravanan et al. Sec. I: 3D-Net's reference
point), undistorted and taken through H^-1 to the ground. Seen from a pole, the bottom edge of
a box is the object's nearest face, not its centre. Precisely: the bottom row v_max of the box
maps to a ground line L (the image row's preimage; for a camera without roll, the line
perpendicular to the optical axis's heading), and the footprint touches L with its extreme
point; the footprint's centre lies a half-extent X beyond L along L's normal n (away from the
camera), and on the ray d from the camera's ground point through g (the box's horizontal
centre is the object's bearing). So c = g + k d with k = X / (n . d). For a box l x w at an
unknown yaw a (uniform) relative to n, X = (l |cos a| + w |sin a|) / 2:

    E[X]   = (l + w) / pi                                      (E|cos a| = E|sin a| = 2 / pi)
    E[X^2] = (l^2 / 2 + w^2 / 2 + 2 l w / pi) / 4              (E cos^2 = 1/2, E|cos a sin a| = 1/pi)
    Var[X] = E[X^2] - E[X]^2   (a car 4.6 x 1.85 m: E = 2.05 m, std 0.46 m)

Size comes from the class prior (``schemas.classes.CLASS_DEFAULT_LWH``); yaw 0 and no velocity:
the RSU tracker estimates both from the track.

Covariance: Sigma = J_c J diag(sigma_u^2, sigma_v^2) J^T J_c^T + (Var[X] / (n . d)^2) d d^T, with
J (2, 2) the Jacobian d(map xy)/d(u, v) of the inverse homography at the contact pixel (see
``homography_jacobian``) and J_c = dc/dg of c = g + k d, k = E[X] / (n . d), with n held fixed
(exact without roll: then all rows map to parallel lines): with r = |g - camera|,
P = I - d d^T, dd/dg = P / r and dk/dg = -(k / (n . d)) n^T P / r,

    J_c = I + (k / r) P - (k / ((n . d) r)) d n^T P.

J grows roughly as r^2 / (h f) along the ray and r / f across it (h the camera height, f the
focal length in px), so the covariance grows with range.
"""

from __future__ import annotations

import numpy as np

from v2i.core.objects import ObjectArray
from schemas.classes import CLASS_DEFAULT_LWH, ObjectClass
from schemas.messages import SOURCE_RSU

from v2i.perception.calibration import Calibration

_UNDISTORT_STEP_PX = 0.5  # central-difference step of the undistortion Jacobian
_MIN_COS = 0.3  # n . d floor: a ray 73 deg off the row normal is beyond any useful pinhole view


def bottom_centre(xyxy: np.ndarray) -> np.ndarray:
    """Bottom-centre pixels (N, 2) of boxes (N, 4) [x1, y1, x2, y2]: ((x1 + x2) / 2, y2)."""
    b = np.asarray(xyxy, dtype=float).reshape(-1, 4)
    return np.column_stack([(b[:, 0] + b[:, 2]) / 2.0, b[:, 3]])


def homography_jacobian(H_px_to_map: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """d(map xy)/d(u, v) (N, 2, 2) of the map point G [u, v, 1]^T at undistorted pixels (N, 2).

    q = G [u, v, 1]^T, x = q1 / q3, y = q2 / q3, so with g_i the rows of G:
        d x_i / d u_j = (G_ij - x_i G_3j) / q3,   i in {x, y}, j in {u, v}.
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    q = np.column_stack([uv, np.ones(len(uv))]) @ H_px_to_map.T  # (N, 3)
    xy = q[:, :2] / q[:, 2:3]
    G = H_px_to_map
    return (G[None, :2, :2] - xy[:, :, None] * G[None, 2:3, :2]) / q[:, 2, None, None]


def _undistort_jacobian(calib: Calibration, uv: np.ndarray) -> np.ndarray:
    """d(undistorted px)/d(raw px) (N, 2, 2) by central differences (identity without distortion)."""
    n = len(uv)
    if not calib.distorted:
        return np.tile(np.eye(2), (n, 1, 1))
    h = _UNDISTORT_STEP_PX
    steps = np.array([[h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]])
    moved = calib.undistort((uv[:, None, :] + steps[None]).reshape(-1, 2)).reshape(n, 4, 2)
    return np.stack([(moved[:, 0] - moved[:, 1]), (moved[:, 2] - moved[:, 3])], axis=-1) / (2.0 * h)


def centre_offset(lwh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (N,) and variance (N,) of a footprint's half-extent X along a direction, at unknown
    (uniform) yaw, for sizes (N, 3) l, w, h (m, m^2)."""
    lwh = np.asarray(lwh, dtype=float).reshape(-1, 3)
    l, w = lwh[:, 0], lwh[:, 1]
    mean = (l + w) / np.pi  # E[(l|cos a| + w|sin a|) / 2]
    second = (0.5 * l**2 + 0.5 * w**2 + 2.0 * l * w / np.pi) / 4.0  # E[X^2]
    return mean, np.maximum(second - mean**2, 0.0)


def _sigma_px(pixel_sigma_px) -> np.ndarray:
    s = np.broadcast_to(np.asarray(pixel_sigma_px, dtype=float), (2,))
    if not np.all(np.isfinite(s)) or np.any(s < 0):
        raise ValueError(f"pixel_sigma_px must be finite and >= 0, got {pixel_sigma_px}")
    return s


def _camera_xy(calib: Calibration, camera_xy) -> np.ndarray:
    if camera_xy is not None:
        return np.asarray(camera_xy, dtype=float).reshape(2)
    if calib.camera_xy is not None:
        return calib.camera_xy
    raise ValueError(f"calibration {calib.camera_id!r} has no full projection (K, rvec, tvec), so the camera's "
                     "ground position is unknown: pass camera_xy (the RSU pole's x, y)")


def ground_contact(calib: Calibration, xyxy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground contact points (N, 2) m of boxes (N, 4) px, their Jacobians d(xy)/d(raw u, v)
    (N, 2, 2), and in_front (N,) bool (False: the box bottom is at or above the horizon)."""
    uv = bottom_centre(xyxy)
    xy, in_front = calib.px_to_map(uv)
    J = homography_jacobian(calib.H_px_to_map, calib.undistort(uv)) @ _undistort_jacobian(calib, uv)
    return xy, J, in_front


def _centre_from_contact(contact: np.ndarray, J: np.ndarray, camera_xy: np.ndarray,
                         lwh: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (N, 2), J_c = dc/dg (N, 2, 2) and the offset's covariance (N, 2, 2) from ground
    contacts g (N, 2), their pixel Jacobians (N, 2, 2) and sizes (N, 3) (module docstring)."""
    offset, offset_var = centre_offset(lwh)
    ray = contact - camera_xy
    r = np.maximum(np.hypot(ray[:, 0], ray[:, 1]), 1e-6)
    d = ray / r[:, None]
    row = J[:, :, 0]  # the ground direction of the image row (moving in u)
    n = np.column_stack([-row[:, 1], row[:, 0]]) / np.maximum(np.hypot(row[:, 0], row[:, 1]), 1e-12)[:, None]
    nd = np.sum(n * d, axis=1)
    n *= np.where(nd < 0, -1.0, 1.0)[:, None]  # away from the camera
    nd = np.maximum(np.abs(nd), _MIN_COS)
    k = offset / nd
    P = np.eye(2)[None] - d[:, :, None] * d[:, None, :]
    dnP = d[:, :, None] * np.einsum("ni,nij->nj", n, P)[:, None, :]  # d n^T P
    Jc = np.eye(2)[None] + (k / r)[:, None, None] * P - (k / (nd * r))[:, None, None] * dnP
    along_var = (offset_var / nd**2)[:, None, None] * d[:, :, None] * d[:, None, :]
    return contact + k[:, None] * d, Jc, along_var


def pixels_to_map(calib: Calibration, xyxy: np.ndarray, cls: np.ndarray, scores: np.ndarray,
                  pixel_sigma_px: float | tuple[float, float] = 1.0, camera_xy=None) -> ObjectArray:
    """Detector boxes (N, 4) px [x1, y1, x2, y2] of classes (N,) and scores (N,) -> objects in map.

    ids -1, sources SOURCE_RSU, confidence = score, size = class prior, z = h / 2, yaw 0, no
    velocity; cov_xy as in the module docstring. ``pixel_sigma_px``: std of the contact pixel,
    one value or (sigma_u, sigma_v). ``camera_xy`` (2,): the camera's ground position (default:
    from the calibration's full projection). Boxes whose bottom is at or above the horizon have
    no ground point and are left out (M <= N objects).
    """
    cls = np.asarray(cls, dtype=np.int64).reshape(-1)
    scores = np.asarray(scores, dtype=float).reshape(-1)
    n = len(cls)
    if np.asarray(xyxy).size != 4 * n or len(scores) != n:
        raise ValueError(f"xyxy (N, 4), cls (N,), scores (N,) expected, got {np.shape(xyxy)}, {cls.shape}, {scores.shape}")
    if n == 0:
        return ObjectArray.empty()
    sigma, camera = _sigma_px(pixel_sigma_px), _camera_xy(calib, camera_xy)
    contact, J, keep = ground_contact(calib, xyxy)
    contact, J, cls, scores, m = contact[keep], J[keep], cls[keep], scores[keep], int(keep.sum())
    lwh = np.array([CLASS_DEFAULT_LWH[ObjectClass(int(c))] for c in cls], dtype=float).reshape(-1, 3)
    centre, Jc, along_var = _centre_from_contact(contact, J, camera, lwh)
    JJ = Jc @ J
    return ObjectArray(
        ids=np.full(m, -1, dtype=np.int64), cls=cls, xy=centre, z=lwh[:, 2] / 2.0, lwh=lwh, yaw=np.zeros(m),
        vxy=np.zeros((m, 2)), cov_xy=JJ @ np.diag(sigma**2) @ np.swapaxes(JJ, 1, 2) + along_var,
        confidence=np.clip(scores, 0.0, 1.0), sources=np.full(m, SOURCE_RSU, dtype=np.int64),
    )
