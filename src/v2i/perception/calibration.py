"""Camera calibration from surveyed point correspondences (Saravanan et al. Sec. II, eq. 1-2), with OpenCV.

N >= 6 pairs pixel (u, v) <-> map point (x, y, z) (map: x east, y north, z up, m), as the
paper selects ">= six point correspondences" between the image and the local map:

- No intrinsics: every point lies on the ground (z = 0) and the ground-plane homography H,
  [u, v, 1]^T ~ H [x, y, 1]^T, comes from ``cv2.findHomography`` with RANSAC (DLT A h = 0,
  ||h|| = 1 on the inliers, eq. 2 restricted to z = 0, then Levenberg-Marquardt on the
  re-projection error).
- Intrinsics K (and distortion) known, from a lab checkerboard or the lens's field of view:
  the full projection x ~ K [R | t] X by ``cv2.solvePnPRansac`` + ``cv2.solvePnPRefineLM`` on
  the inliers; points may carry heights (building corners, signal heads) or all lie on the
  ground. The ground homography is the projection without its z column, H = K [r1 r2 t].

H maps to undistorted pixels (a distorted click is undistorted with K, dist first). H is kept
at unit Frobenius norm with the sign that gives ground points in front of the camera a
positive third coordinate w (w ~ depth z_c): the image's bottom-centre pixel, which every
roadside camera sees on the ground, defines it. Re-projection error: Euclidean pixel distance
per point; ``reprojection_px`` is the RMS over the inliers, ``reprojection_mean_px`` their mean.

File (JSON, ``schema: v2i-calibration/1``): camera id, image size [width, height], H_map_to_px,
optional K (3, 3), dist (4, 5, 8, 12 or 14), rvec (3,), tvec (3,) (OpenCV: X_c = R(rvec) X + t),
the errors, the point counts and the points file it came from.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from v2i.core.files import FileRefused, MiB, read_text
from v2i.runtime.config import ConfigError, validate

SCHEMA = "v2i-calibration/1"
MIN_POINTS = 6  # Saravanan et al. Sec. II: at least six point correspondences
DEFAULT_RANSAC_PX = 3.0  # inlier threshold: ~4 sigma of a careful click (0.5-1 px)
_COLLINEAR_RATIO = 1e-3  # second / first singular value of centred points below this: on a line
_SINGULAR_COND = 1e12  # condition number of the unit-norm H above which it is singular
_DIST_LENGTHS = (4, 5, 8, 12, 14)  # OpenCV distortion vector lengths
CALIBRATION_LIMIT_BYTES = 1 * MiB  # a calibration file: a homography, intrinsics and points, ~2 kB


class CalibrationError(ConfigError):
    """Points that cannot calibrate a camera, or a calibration file that cannot be used."""


def _hom(xy: np.ndarray) -> np.ndarray:
    return np.column_stack([xy, np.ones(len(xy))])


def _normalised(H: np.ndarray, width: int, height: int) -> np.ndarray:
    """H scaled to unit Frobenius norm, sign such that the bottom-centre pixel maps in front.

    A pixel p maps to the ground point q = H^-1 p; then H (q / q3) = p / q3, so that point's
    w is 1 / q3: in front (w > 0) iff q3 > 0.
    """
    H = H / np.linalg.norm(H)
    q = np.linalg.solve(H, np.array([width / 2.0, height - 0.5, 1.0]))
    return -H if q[2] < 0 else H


def _check_matrix(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != shape:
        raise CalibrationError(f"{name}: shape {arr.shape}, expected {shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{name}: non-finite values")
    return arr


@dataclass(frozen=True, eq=False)
class Calibration:
    """A calibrated camera: ground homography (3, 3) map -> undistorted px and its inverse,
    image size (px), optional full projection K (3, 3), dist (k,), rvec (3,), tvec (3,)."""

    camera_id: str
    width: int
    height: int
    H_map_to_px: np.ndarray
    reprojection_px: float  # RMS over the inliers (px)
    reprojection_mean_px: float  # mean over the inliers (px)
    n_points: int
    n_inliers: int
    K: np.ndarray | None = None
    dist: np.ndarray | None = None
    rvec: np.ndarray | None = None
    tvec: np.ndarray | None = None
    points_file: str = ""
    H_px_to_map: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(f"image_size: must be positive, got {self.width} x {self.height}")
        H = _check_matrix("H_map_to_px", self.H_map_to_px, (3, 3))
        if not np.linalg.norm(H) > 0 or np.linalg.cond(H / np.linalg.norm(H)) > _SINGULAR_COND:
            raise CalibrationError("H_map_to_px: singular (it maps the ground plane onto a line or a point)")
        object.__setattr__(self, "H_map_to_px", _normalised(H, self.width, self.height))
        object.__setattr__(self, "H_px_to_map", np.linalg.inv(self.H_map_to_px))
        self._check_projection()

    def _check_projection(self) -> None:
        given = {n: getattr(self, n) is not None for n in ("K", "rvec", "tvec")}
        if any(given.values()) and not all(given.values()):
            raise CalibrationError(f"K, rvec and tvec go together; missing: {[n for n, g in given.items() if not g]}")
        if self.dist is not None and self.K is None:
            raise CalibrationError("dist: given without K")
        if self.K is None:
            return
        K = _check_matrix("K", self.K, (3, 3))
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0:
            raise CalibrationError("K: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
        dist = np.zeros(5) if self.dist is None else np.asarray(self.dist, dtype=float).ravel()
        if len(dist) not in _DIST_LENGTHS or not np.all(np.isfinite(dist)):
            raise CalibrationError(f"dist: {len(dist)} finite values expected to be one of {_DIST_LENGTHS}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "rvec", _check_matrix("rvec", self.rvec, (3,)))
        object.__setattr__(self, "tvec", _check_matrix("tvec", self.tvec, (3,)))
        H = _normalised(self.K @ np.column_stack([self.R[:, 0], self.R[:, 1], self.tvec]), self.width, self.height)
        if np.max(np.abs(H - self.H_map_to_px)) > 1e-6:
            raise CalibrationError("H_map_to_px disagrees with K [r1 r2 t] of K, rvec, tvec")

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) px."""
        return self.width, self.height

    @property
    def has_projection(self) -> bool:
        """True when the full projection (K, dist, rvec, tvec) is known."""
        return self.K is not None

    @property
    def R(self) -> np.ndarray:
        """World-to-camera rotation (3, 3) of rvec (Rodrigues)."""
        if self.rvec is None:
            raise CalibrationError(f"calibration {self.camera_id!r} has no full projection (no K, rvec, tvec)")
        return cv2.Rodrigues(self.rvec)[0]

    @property
    def camera_position_m(self) -> np.ndarray | None:
        """Camera centre C (3,) in map, C = -R^T t; None without the full projection."""
        return None if self.rvec is None else -self.R.T @ self.tvec

    @property
    def camera_xy(self) -> np.ndarray | None:
        """The ground point (2,) below the camera centre; None without the full projection."""
        c = self.camera_position_m
        return None if c is None else c[:2]

    @property
    def distorted(self) -> bool:
        return self.dist is not None and bool(np.any(self.dist != 0.0))

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Raw pixels (N, 2) -> undistorted pixels (N, 2) of the same K (identity without dist)."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        if not self.distorted or len(uv) == 0:
            return uv
        return cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, self.dist, P=self.K).reshape(-1, 2)

    def map_to_px(self, xy: np.ndarray) -> np.ndarray:
        """Ground points (N, 2) m -> undistorted pixels (N, 2): p ~ H [x, y, 1]^T."""
        p = _hom(np.asarray(xy, dtype=float).reshape(-1, 2)) @ self.H_map_to_px.T
        return p[:, :2] / p[:, 2:3]

    def px_to_map(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw pixels (N, 2) -> ground points (N, 2) m and in_front (N,) bool.

        q = H^-1 [u, v, 1]^T (undistorted u, v), xy = q[:2] / q3; q3 <= 0: the pixel is at or
        above the horizon, its ray never meets the ground in front of the camera: xy NaN.
        """
        q = _hom(self.undistort(uv)) @ self.H_px_to_map.T
        in_front = q[:, 2] > 0
        return q[:, :2] / np.where(in_front, q[:, 2], np.nan)[:, None], in_front

    def project(self, points_m: np.ndarray) -> np.ndarray:
        """Map points (N, 3) -> raw (distorted) pixels (N, 2) through the full projection."""
        pts = np.asarray(points_m, dtype=float).reshape(-1, 3)
        uv, _ = cv2.projectPoints(pts, self.rvec, self.tvec, self.K, self.dist)
        return uv.reshape(-1, 2)


# ---------------------------------------------------------------- fitting


def _check_points(px, map_xyz) -> tuple[np.ndarray, np.ndarray]:
    """Validated pixels (N, 2) and map points (N, 3); CalibrationError naming points 1..N."""
    px = np.ascontiguousarray(px, dtype=float)  # OpenCV wants contiguous float64 rows
    xyz = np.ascontiguousarray(map_xyz, dtype=float)
    if xyz.ndim == 2 and xyz.shape[1] == 2:
        xyz = np.column_stack([xyz, np.zeros(len(xyz))])
    if px.ndim != 2 or px.shape[1] != 2 or xyz.ndim != 2 or xyz.shape[1] != 3 or len(px) != len(xyz):
        raise CalibrationError(f"pixels (N, 2) and map points (N, 3) expected, got {px.shape} and {xyz.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(np.hstack([px, xyz])), axis=1))
    if len(bad):
        raise CalibrationError(f"non-finite coordinates in point(s) {(bad + 1).tolist()}")
    if len(px) < MIN_POINTS:
        raise CalibrationError(f"{len(px)} point correspondences; at least {MIN_POINTS} are needed")
    for name, arr in (("pixel", px), ("map point", xyz)):
        d = np.linalg.norm(arr[:, None] - arr[None], axis=-1)
        np.fill_diagonal(d, np.inf)
        i, j = np.unravel_index(np.argmin(d), d.shape)
        if d[i, j] < 1e-6:
            raise CalibrationError(f"points {min(i, j) + 1} and {max(i, j) + 1} have the same {name}")
    return px, xyz


def _rank_problem(points: np.ndarray, what: str, dims: int) -> str | None:
    """Why ``points`` (N, D) cannot span ``dims`` dimensions (on a line), or None."""
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    if s[0] <= 0 or s[dims - 1] < _COLLINEAR_RATIO * s[0]:
        return f"the {what} are (nearly) collinear: a line does not fix a plane's mapping"
    return None


def _fit_homography(px: np.ndarray, xyz: np.ndarray, ransac_px: float) -> np.ndarray:
    """H (3, 3) ground -> px by cv2.findHomography with RANSAC (map points must have z = 0)."""
    if np.any(xyz[:, 2] != 0.0):
        rows = (np.flatnonzero(xyz[:, 2] != 0.0) + 1).tolist()
        raise CalibrationError(f"point(s) {rows} are above the ground (z != 0): without intrinsics K only "
                               "ground points fit a homography; give K (solvePnP) or drop them")
    H, _ = cv2.findHomography(xyz[:, :2], px, cv2.RANSAC, ransacReprojThreshold=ransac_px,
                              maxIters=5000, confidence=0.9999)
    if H is None:
        raise CalibrationError("cv2.findHomography found no homography: the points are degenerate")
    # Least squares + LM on every point within a threshold of the current H; the first pass
    # at twice the threshold lets back in a good point that the minimal RANSAC model, fitted
    # without it, extrapolated badly (a lone point at the image edge); the later passes reject
    # again what the refit still puts beyond the threshold.
    for scale in (2.0, 1.0, 1.0):
        p = _hom(xyz[:, :2]) @ H.T
        keep = np.linalg.norm(p[:, :2] / p[:, 2:3] - px, axis=1) <= scale * ransac_px
        refit, _ = cv2.findHomography(xyz[keep, :2], px[keep], 0) if keep.sum() >= 4 else (None, None)
        if refit is None:
            break
        H = refit
    return H


def _fit_pnp(px: np.ndarray, xyz: np.ndarray, K: np.ndarray, dist: np.ndarray,
             ransac_px: float) -> tuple[np.ndarray, np.ndarray]:
    """rvec, tvec (3,) of the full projection: solvePnPRansac, then LM on the inliers."""
    ok, rvec, tvec, inl = cv2.solvePnPRansac(xyz, px, K, dist, iterationsCount=2000, reprojectionError=ransac_px,
                                             confidence=0.9999, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or inl is None or len(inl) < 4:
        raise CalibrationError("cv2.solvePnPRansac found no camera pose consistent with the points")
    for scale in (2.0, 1.0, 1.0):  # LM on the points within (scale x) the threshold, as in _fit_homography
        keep = _errors_pnp(px, xyz, K, dist, rvec, tvec) <= scale * ransac_px
        if keep.sum() < 4:
            break
        rvec, tvec = cv2.solvePnPRefineLM(xyz[keep], px[keep], K, dist, rvec, tvec)
    return rvec.ravel(), tvec.ravel()


def _errors_pnp(px, xyz, K, dist, rvec, tvec) -> np.ndarray:
    uv, _ = cv2.projectPoints(xyz, rvec, tvec, K, dist)
    return np.linalg.norm(uv.reshape(-1, 2) - px, axis=1)


def reprojection_errors(calib: Calibration, px, map_xyz) -> np.ndarray:
    """Per-point re-projection error (N,) px of a calibration on points (N, 2), (N, 3).

    Full projection: |project(X) - raw px|; homography only: |H [x, y, 1] - undistorted px|.
    """
    px, xyz = np.ascontiguousarray(px, dtype=float).reshape(-1, 2), np.ascontiguousarray(map_xyz, dtype=float)
    xyz = np.column_stack([xyz, np.zeros(len(xyz))]) if xyz.shape[1:] == (2,) else xyz.reshape(-1, 3)
    if calib.has_projection:
        return np.linalg.norm(calib.project(xyz) - px, axis=1)
    return np.linalg.norm(calib.map_to_px(xyz[:, :2]) - calib.undistort(px), axis=1)


def fit_calibration(px, map_xyz, K=None, dist=None, ransac_px: float = DEFAULT_RANSAC_PX, *,
                    image_size: tuple[int, int], camera_id: str = "camera", points_file: str = "") -> Calibration:
    """Calibrate from pixels (N, 2) raw px and map points (N, 3) (or (N, 2): z = 0), N >= 6.

    Without K: ground homography (RANSAC); with K (3, 3) (and dist): full projection (PnP
    RANSAC + LM). Inliers: re-projection error <= ``ransac_px``; at least 6 must remain.
    CalibrationError for too few, non-finite, duplicate or collinear points.
    """
    px, xyz = _check_points(px, map_xyz)
    if not ransac_px > 0:
        raise CalibrationError(f"ransac_px must be > 0, got {ransac_px}")
    width, height = (int(v) for v in image_size)
    problem = _rank_problem(px, "pixels", 2) or (
        _rank_problem(xyz, "map points", 2) if K is not None else _rank_problem(xyz[:, :2], "map points", 2))
    if problem:
        raise CalibrationError(problem)
    if K is None:
        if dist is not None:
            raise CalibrationError("distortion needs the intrinsics K it belongs to")
        calib = Calibration(camera_id, width, height, _fit_homography(px, xyz, ransac_px), 0.0, 0.0, len(px), 0)
    else:
        K = _check_matrix("K", K, (3, 3))
        d = np.zeros(5) if dist is None else np.asarray(dist, dtype=float).ravel()
        rvec, tvec = _fit_pnp(px, xyz, K, d, ransac_px)
        H = K @ np.column_stack([cv2.Rodrigues(rvec)[0][:, :2], tvec])
        calib = Calibration(camera_id, width, height, H, 0.0, 0.0, len(px), 0, K, d, rvec, tvec)
    return _with_errors(calib, px, xyz, ransac_px, points_file)


def _with_errors(calib: Calibration, px, xyz, ransac_px: float, points_file: str) -> Calibration:
    """The calibration with its inlier statistics; CalibrationError when < 6 inliers or any is behind."""
    err = reprojection_errors(calib, px, xyz)
    inl = err <= ransac_px
    if inl.sum() < MIN_POINTS:
        worst = (np.argsort(-err)[: len(err) - int(inl.sum())] + 1).tolist()
        raise CalibrationError(f"only {int(inl.sum())} of {len(err)} points agree within {ransac_px:g} px "
                               f"(at least {MIN_POINTS} needed); worst points: {worst}")
    if calib.has_projection:
        depth = (xyz[inl] @ calib.R.T + calib.tvec)[:, 2]  # z_c = (R X + t)_3
    else:
        depth = (_hom(xyz[inl, :2]) @ calib.H_map_to_px.T)[:, 2]  # w ~ z_c, > 0 in front
    if np.any(depth <= 0):
        raise CalibrationError("some inlier points lie behind the camera or beyond its horizon: check the map "
                               "coordinates (x east, y north) and the pixel order (u right, v down)")
    return Calibration(
        calib.camera_id, calib.width, calib.height, calib.H_map_to_px, float(np.sqrt(np.mean(err[inl] ** 2))),
        float(np.mean(err[inl])), len(err), int(inl.sum()), calib.K, calib.dist, calib.rvec, calib.tvec, points_file)


# ---------------------------------------------------------------- file


Finite = Annotated[float, Field(allow_inf_nan=False)]
NonNeg = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
Vec3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]
Mat3 = Annotated[list[Vec3], Field(min_length=3, max_length=3)]


class _CalibrationFile(BaseModel):
    """The JSON layout of a calibration file (strict: unknown keys rejected)."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    schema_id: Literal["v2i-calibration/1"] = Field(alias="schema")
    camera_id: str = Field(min_length=1)
    image_size: tuple[Annotated[int, Field(gt=0, le=16384)], Annotated[int, Field(gt=0, le=16384)]]
    H_map_to_px: Mat3
    K: Mat3 | None = None
    dist: Annotated[list[Finite], Field(min_length=4, max_length=14)] | None = None
    rvec: Vec3 | None = None
    tvec: Vec3 | None = None
    reprojection_rms_px: NonNeg
    reprojection_mean_px: NonNeg
    n_points: int = Field(ge=MIN_POINTS)
    n_inliers: int = Field(ge=MIN_POINTS)
    points_file: str = ""


def _as_list(arr) -> list | None:
    return None if arr is None else np.asarray(arr, dtype=float).tolist()


def save_calibration(calib: Calibration, path: str | Path) -> Path:
    """Write ``calib`` as JSON (one key per line, floats exact) and return the path."""
    data = {
        "schema": SCHEMA, "camera_id": calib.camera_id, "image_size": [calib.width, calib.height],
        "H_map_to_px": _as_list(calib.H_map_to_px), "K": _as_list(calib.K), "dist": _as_list(calib.dist),
        "rvec": _as_list(calib.rvec), "tvec": _as_list(calib.tvec),
        "reprojection_rms_px": calib.reprojection_px, "reprojection_mean_px": calib.reprojection_mean_px,
        "n_points": calib.n_points, "n_inliers": calib.n_inliers, "points_file": calib.points_file,
    }
    lines = [f"  {json.dumps(k)}: {json.dumps(v)}" for k, v in data.items() if v is not None]
    path = Path(path)
    path.write_text("{\n" + ",\n".join(lines) + "\n}\n", encoding="utf-8")
    return path


def load_calibration(path: str | Path) -> Calibration:
    """A calibration file, validated: CalibrationError naming the file and the bad field."""
    source = f"calibration {path}"
    try:
        data = json.loads(read_text(path, CALIBRATION_LIMIT_BYTES, "calibration"))
    except FileRefused as exc:
        raise CalibrationError(str(exc)) from None
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{source}: not valid JSON ({exc})") from None
    f = validate(_CalibrationFile, data, source, CalibrationError)
    if f.n_inliers > f.n_points:
        raise CalibrationError(f"invalid {source}: n_inliers {f.n_inliers} > n_points {f.n_points}")
    try:
        return Calibration(f.camera_id, f.image_size[0], f.image_size[1], np.array(f.H_map_to_px),
                           f.reprojection_rms_px, f.reprojection_mean_px, f.n_points, f.n_inliers,
                           None if f.K is None else np.array(f.K), None if f.dist is None else np.array(f.dist),
                           None if f.rvec is None else np.array(f.rvec), None if f.tvec is None else np.array(f.tvec),
                           f.points_file)
    except CalibrationError as exc:
        raise CalibrationError(f"invalid {source}: {exc}") from None


def bundled_calibration_dir() -> Path:
    """The folder of the shipped calibrations (one per bundled scenario's RSU camera, made from points
    surveyed in its simulated world: ``tools/survey_points.py``), ``perception/calibrations``."""
    return Path(str(resources.files("v2i.perception") / "calibrations"))


def calibration_path(scenario: str | Path) -> Path | None:
    """The camera calibration of a scenario: the shipped ``<name>.calib.json`` of a bundled one,
    else ``<file>.calib.json`` beside a scenario YAML; None when there is none."""
    shipped = bundled_calibration_dir() / f"{scenario}.calib.json"
    if "/" not in str(scenario) and shipped.is_file():
        return shipped
    beside = Path(scenario).with_suffix(".calib.json")
    return beside if Path(scenario).suffix in (".yaml", ".yml") and beside.is_file() else None
