"""``v2i camera calibrate``: fit a camera calibration from surveyed pixel <-> map points.

Reads a points CSV, fits (``v2i.perception.calibration.fit_calibration``), prints the
re-projection error per point and in summary, and writes the calibration JSON the RSU loads.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from v2i.core.files import FileRefused, KiB, MiB, read_text
from v2i.perception.calibration import (
    DEFAULT_RANSAC_PX,
    Calibration,
    CalibrationError,
    fit_calibration,
    reprojection_errors,
    save_calibration,
)

POINTS_LIMIT_BYTES = 1 * MiB  # a points file: tens of clicked correspondences, ~40 bytes a line
INTRINSICS_LIMIT_BYTES = 64 * KiB  # an intrinsics JSON: K, dist and the image size
HEADERS = (("u_px", "v_px", "x_m", "y_m"), ("u_px", "v_px", "x_m", "y_m", "z_m"))

DESCRIPTION = """\
Fit a camera calibration from >= 6 surveyed correspondences between pixels and map points
(Saravanan et al. Sec. II) and write the calibration file the RSU loads (--calibration of `v2i rsu`).

Points file (CSV): a header line, then one point per line; '#' starts a comment (whole line
or after the values); blank lines are skipped.
    u_px,v_px,x_m,y_m[,z_m]
    412.3,288.9,-10.00,-7.00      # kerb corner, south-west
    201.7,140.2,-10.50,10.50,3.0  # building corner 3 m up (needs intrinsics)
u_px, v_px: the pixel clicked in the raw image (u right, v down, as OpenCV and the
detector report them); x_m, y_m, z_m: the surveyed point in the map frame (x east, y north, z up, m).

Without intrinsics only the points on the ground (z_m = 0 or no z_m column) are used (the
others are left out, with a note): the ground-plane homography is fitted with RANSAC
(cv2.findHomography) and --image-size is required. With intrinsics (--intrinsics FILE, or --fov-deg and --image-size for a pinhole
with square pixels, principal point at the centre and no distortion) the full projection is
fitted (cv2.solvePnPRansac + LM refinement); points may then have heights, and the file also
holds K, dist, rvec, tvec and so the camera's position. Intrinsics file (JSON):
    {"K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "dist": [k1, k2, p1, p2, k3], "image_size": [640, 384]}
("dist" and "image_size" optional). Points further than --ransac-px from the fitted model are
outliers (a mis-click) and left out of the fit; the re-projection error is reported over the
inliers as RMS and mean."""


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add ``calibrate`` to the ``v2i camera`` subparsers object and return its parser."""
    p = subparsers.add_parser("calibrate", help="fit a camera calibration from surveyed pixel <-> map points",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--points", required=True, metavar="FILE", help="points CSV: u_px,v_px,x_m,y_m[,z_m] (see above)")
    p.add_argument("--out", required=True, metavar="CALIB.json", help="calibration file to write")
    p.add_argument("--intrinsics", metavar="K.json", help="known intrinsics K (and dist, image_size) as JSON")
    p.add_argument("--fov-deg", type=float, metavar="DEG",
                   help="horizontal field of view of a pinhole camera: K from it and --image-size")
    p.add_argument("--image-size", metavar="WxH", help="image width x height in px, e.g. 640x384")
    p.add_argument("--camera-id", metavar="ID", help="camera id stored in the file (default: the points file's name)")
    p.add_argument("--ransac-px", type=float, default=DEFAULT_RANSAC_PX,
                   help="inlier threshold on the re-projection error, px (default %(default)s)")
    p.set_defaults(func=run)
    return p


def read_points(path: str | Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Pixels (N, 2), map points (N, 3) (z = 0 without a z_m column) and each line's comment."""
    rows, notes, header = [], [], None
    try:
        lines = read_text(path, POINTS_LIMIT_BYTES, "points file").splitlines()
    except FileRefused as exc:
        raise CalibrationError(str(exc)) from None
    for number, line in enumerate(lines, 1):
        text, _, note = line.partition("#")
        if not text.strip():
            continue
        cells = [c.strip() for c in text.split(",")]
        if header is None:
            if tuple(cells) not in HEADERS:
                raise CalibrationError(f"{path}:{number}: header must be 'u_px,v_px,x_m,y_m' or "
                                       f"'u_px,v_px,x_m,y_m,z_m', got {text.strip()!r}")
            header = cells
            continue
        if len(cells) != len(header):
            raise CalibrationError(f"{path}:{number}: {len(cells)} values, the header has {len(header)}")
        try:
            values = [float(c) for c in cells]
        except ValueError:
            raise CalibrationError(f"{path}:{number}: not a number in {text.strip()!r}") from None
        if not all(math.isfinite(v) for v in values):
            raise CalibrationError(f"{path}:{number}: non-finite value in {text.strip()!r}")
        rows.append(values + [0.0] * (5 - len(values)))
        notes.append(note.strip())
    if header is None:
        raise CalibrationError(f"{path}: no header line 'u_px,v_px,x_m,y_m[,z_m]'")
    data = np.array(rows, dtype=float).reshape(-1, 5)
    return data[:, :2], data[:, 2:], notes


def _image_size(text: str) -> tuple[int, int]:
    w, sep, h = text.lower().partition("x")
    try:
        size = (int(w), int(h))
    except ValueError:
        size = (0, 0)
    if not sep or min(size) <= 0:
        raise ValueError(f"--image-size: WIDTHxHEIGHT in px expected, e.g. 640x384, got {text!r}")
    return size


def _read_json(path: str, limit_bytes: int, what: str):
    """The JSON in the regular file ``path`` of at most ``limit_bytes``; ValueError naming it otherwise."""
    try:
        return json.loads(read_text(path, limit_bytes, what))
    except FileRefused as exc:
        raise ValueError(str(exc)) from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{what} {path}: not valid JSON ({exc})") from None


def _intrinsics(args) -> tuple[np.ndarray | None, np.ndarray | None, tuple[int, int] | None, str]:
    """K, dist, image size and a description of where they came from, from the arguments."""
    size = _image_size(args.image_size) if args.image_size else None
    if args.intrinsics and args.fov_deg is not None:
        raise ValueError("give --intrinsics or --fov-deg, not both")
    if args.intrinsics:
        data = _read_json(args.intrinsics, INTRINSICS_LIMIT_BYTES, "intrinsics file")
        try:
            K = np.array(data["K"], dtype=float)
            dist = np.array(data.get("dist", [0.0] * 5), dtype=float).ravel()
            size = size or tuple(int(v) for v in data["image_size"])
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"--intrinsics {args.intrinsics}: needs JSON with 'K' (3x3), optional 'dist' and "
                             f"'image_size' (or --image-size): {type(exc).__name__}: {exc}") from None
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or not np.all(np.isfinite(dist)) or len(size) != 2:
            raise ValueError(f"--intrinsics {args.intrinsics}: K must be 3x3 and K, dist finite")
        return K, dist, size, f"K from {args.intrinsics}"
    if args.fov_deg is not None:
        if size is None or not 0.0 < args.fov_deg < 180.0:
            raise ValueError("--fov-deg needs --image-size and 0 < fov < 180 deg")
        f = 0.5 * size[0] / math.tan(math.radians(args.fov_deg) / 2.0)  # f = (W / 2) / tan(hfov / 2)
        K = np.array([[f, 0.0, size[0] / 2.0], [0.0, f, size[1] / 2.0], [0.0, 0.0, 1.0]])
        return K, None, size, f"K from --fov-deg {args.fov_deg:g} at {size[0]}x{size[1]}"
    if size is None:
        raise ValueError("--image-size is required without --intrinsics")
    return None, None, size, "no intrinsics"


def _report(calib: Calibration, px: np.ndarray, xyz: np.ndarray, numbers: np.ndarray, notes: list[str],
            ransac_px: float) -> str:
    """Per-point table (numbers as in the file) and the summary of the re-projection error."""
    err = reprojection_errors(calib, px, xyz)
    lines = [f"{'#':>3} {'u_px':>8} {'v_px':>8} {'x_m':>9} {'y_m':>9} {'z_m':>6} {'err_px':>7}"]
    for i, p, x, e, note in zip(numbers, px, xyz, err, notes):
        flag = "  OUTLIER" if e > ransac_px else ""
        tail = f"  # {note}" if note else ""
        lines.append(f"{i:>3} {p[0]:8.1f} {p[1]:8.1f} {x[0]:9.2f} {x[1]:9.2f} {x[2]:6.2f} {e:7.2f}{flag}{tail}")
    inl = err <= ransac_px
    lines.append(f"re-projection error over {calib.n_inliers} of {calib.n_points} points (inliers, <= {ransac_px:g} px): "
                 f"RMS {calib.reprojection_px:.2f} px, mean {calib.reprojection_mean_px:.2f} px, "
                 f"max {err[inl].max():.2f} px")
    if calib.camera_position_m is not None:
        c = calib.camera_position_m
        lines.append(f"camera centre in map: x {c[0]:.2f} m, y {c[1]:.2f} m, z {c[2]:.2f} m")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Fit, print the errors and write the calibration file; 0 on success (errors raise ValueError)."""
    if not args.ransac_px > 0:
        raise ValueError(f"--ransac-px must be > 0, got {args.ransac_px}")
    K, dist, size, source = _intrinsics(args)
    px, xyz, notes = read_points(args.points)
    numbers = np.arange(1, len(px) + 1)  # as in the file, for the messages
    above = xyz[:, 2] != 0.0
    if K is None and above.any():  # a homography is a map of the ground plane only
        print(f"note: without intrinsics the {int(above.sum())} points above the ground (z_m != 0) are left out: "
              f"{numbers[above].tolist()}")
        px, xyz, numbers, notes = px[~above], xyz[~above], numbers[~above], [n for n, a in zip(notes, above) if not a]
    camera_id = args.camera_id or Path(args.points).name.split(".")[0]
    try:
        calib = fit_calibration(px, xyz, K, dist, args.ransac_px, image_size=size, camera_id=camera_id,
                                points_file=Path(args.points).name)
    except CalibrationError as exc:
        where = f" (points numbered among the {len(px)} on the ground)" if above.any() and K is None else ""
        raise CalibrationError(f"{args.points}: {exc}{where}") from None
    method = "full projection (solvePnP RANSAC + LM)" if K is not None else "ground homography (findHomography RANSAC)"
    print(f"{args.points}: {len(px)} points; {method}; {source}")
    print(_report(calib, px, xyz, numbers, notes, args.ransac_px))
    save_calibration(calib, args.out)
    print(f"wrote {args.out}")
    return 0
