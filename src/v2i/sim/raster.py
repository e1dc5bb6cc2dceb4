"""Z-buffered rasteriser of textured planar faces for an ideal pinhole canvas (numpy + OpenCV).

A face is a planar polygon in camera coordinates with a texture laid on its plane by a
texel -> canvas homography H = K [R e_s, R e_t, R o + t] (o the map point of texel (0, 0)'s
centre, e_s and e_t the map vectors of one texel step). Faces crossing the view frustum are
clipped in camera coordinates (Sutherland-Hodgman) before projection, so a face that passes
behind the camera is drawn correctly. Depth test: on a plane n . X = c (camera frame) the
inverse depth is affine in the pixel, 1 / z = (n^T K^-1 [u, v, 1]^T) / c, so each face's
1 / z over its bounding box is three numbers; a pixel is drawn where its 1 / z exceeds the
buffer's (nearer). This is exact per pixel, unlike a painter's sort of whole faces.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

SKY_ID, GROUND_ID, BUILDING_ID = -1, -2, -3
NEAR_M = 0.05
MARGIN_PX = 4.0


@dataclass
class Target:
    """What is drawn into: ``image`` (H, W, 3) uint8 BGR, ``inv_depth`` (H, W) float32 (1 / z_c,
    0 for sky) and ``ids`` (H, W) int32 (body id, or SKY_ID / GROUND_ID / BUILDING_ID)."""

    image: np.ndarray
    inv_depth: np.ndarray
    ids: np.ndarray

    def copy(self) -> Target:
        return Target(self.image.copy(), self.inv_depth.copy(), self.ids.copy())


def frustum_planes(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Planes (5, 4) [n, d] of the view volume in camera coordinates, inside n . X + d >= 0:
    z >= NEAR_M and MARGIN_PX-widened image borders, e.g. u >= -m <=> f x + (c_x + m) z >= 0."""
    f, cx, cy, m = K[0, 0], K[0, 2], K[1, 2], MARGIN_PX
    return np.array([
        [0.0, 0.0, 1.0, -NEAR_M],
        [f, 0.0, cx + m, 0.0],
        [-f, 0.0, width - 1 + m - cx, 0.0],
        [0.0, f, cy + m, 0.0],
        [0.0, -f, height - 1 + m - cy, 0.0],
    ])


def clip_polygon(points_c: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """A planar polygon (K, 3) (camera frame) clipped to ``planes`` (P, 4): (M, 3), M may be 0."""
    d = points_c @ planes[:, :3].T + planes[:, 3]  # (K, P) signed distances
    if np.all(d >= 0):
        return points_c
    if np.any(np.all(d < 0, axis=0)):
        return points_c[:0]
    poly = points_c
    for k in np.flatnonzero(np.any(d < 0, axis=0)):
        if len(poly) == 0:
            break
        dist = poly @ planes[k, :3] + planes[k, 3]
        out = []
        for i in range(len(poly)):
            j = (i + 1) % len(poly)
            if dist[i] >= 0:
                out.append(poly[i])
            if (dist[i] >= 0) != (dist[j] >= 0):  # edge crosses: P = P_i + s (P_j - P_i), s = d_i / (d_i - d_j)
                s = dist[i] / (dist[i] - dist[j])
                out.append(poly[i] + s * (poly[j] - poly[i]))
        poly = np.array(out).reshape(-1, 3)
    return poly


def project_ideal(K: np.ndarray, points_c: np.ndarray) -> np.ndarray:
    """Camera points (M, 3), z > 0 -> canvas pixels (M, 2): u = f x / z + c_x."""
    return points_c[:, :2] / points_c[:, 2:3] * K[0, 0] + K[:2, 2]


def inverse_depth_plane(K_inv: np.ndarray, normal_c: np.ndarray, point_c: np.ndarray) -> np.ndarray:
    """(3,) a, b, e with 1 / z = a u + b v + e on the plane through ``point_c`` with ``normal_c``."""
    return (normal_c @ K_inv) / float(normal_c @ point_c)


def texel_homography(K: np.ndarray, R: np.ndarray, t: np.ndarray, origin_m, e_s_m, e_t_m) -> np.ndarray:
    """H (3, 3): level-0 texel (i, j, 1) -> canvas pixel, for texel centres at o + i e_s + j e_t."""
    return K @ np.column_stack([R @ e_s_m, R @ e_t_m, R @ np.asarray(origin_m, float) + t])


def mip_scale(level: int) -> np.ndarray:
    """S_L (3, 3): level-L texel -> level-0 texel, i_0 = 2^L (i_L + 1/2) - 1/2 (area halving)."""
    s = 2.0**level
    return np.array([[s, 0.0, 0.5 * s - 0.5], [0.0, s, 0.5 * s - 0.5], [0.0, 0.0, 1.0]])


def texels_per_pixel(H: np.ndarray, uv: np.ndarray) -> float:
    """Geometric-mean texel footprint of a canvas pixel at ``uv`` (2,): sqrt|det J| of H^-1, and
    for a homography M, det J(p) = det M / (m_3 . p)^3."""
    M = np.linalg.inv(H)
    w = M[2] @ np.array([uv[0], uv[1], 1.0])
    return float(np.sqrt(abs(np.linalg.det(M) / w**3)))


def pick_level(levels: tuple, footprint: float, bias: float = 0.3) -> int:
    return int(np.clip(np.floor(np.log2(max(footprint, 1e-9)) + bias), 0, len(levels) - 1))


def colour_transform(gain: float, fog: float, haze_bgr, channels: int) -> np.ndarray:
    """M (3, channels + 1) for cv2.transform: out = gain (1 - fog) in + fog haze (alpha dropped)."""
    M = np.zeros((3, channels + 1), np.float32)
    M[np.arange(3), np.arange(3)] = gain * (1.0 - fog)
    M[:, -1] = fog * np.asarray(haze_bgr, np.float32)
    return M


def bbox_of(uv: np.ndarray, width: int, height: int) -> tuple[int, int, int, int] | None:
    """Integer pixel box [x0, x1) x [y0, y1) covering points (M, 2), clipped; None if empty."""
    x0, y0 = np.floor(uv.min(axis=0)).astype(int)
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 1
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    return None if x1 <= x0 or y1 <= y0 else (x0, y0, x1, y1)


@dataclass(frozen=True)
class Face:
    """A clipped face ready to draw: canvas polygon (M, 2), 1 / z plane (3,), level-0 texel ->
    canvas homography (3, 3), texture mip levels, shading gain and fog fraction toward ``haze``."""

    uv: np.ndarray
    inv_depth: np.ndarray
    H: np.ndarray
    levels: tuple
    gain: float
    fog: float
    haze: tuple


def draw_face(target: Target, face: Face, body_id: int, union: tuple | None = None) -> None:
    """Draw ``face`` with a depth test; OR its covered pixels (before the test) into ``union``
    = (mask (h, w) bool, x0, y0) if given (the body's unoccluded silhouette)."""
    height, width = target.ids.shape
    box = bbox_of(face.uv, width, height)
    if box is None:
        return
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    mask = np.zeros((h, w), np.uint8)
    cv2.fillPoly(mask, [np.round((face.uv - (x0, y0)) * 16).astype(np.int32)], 1, cv2.LINE_8, 4)
    centre = face.uv.mean(axis=0)
    level = pick_level(face.levels, texels_per_pixel(face.H, centre))
    shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
    tex = face.levels[level]
    warped = cv2.warpPerspective(tex, shift @ face.H @ mip_scale(level), (w, h), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)
    covered = mask.view(bool)
    if tex.shape[2] == 4:
        covered &= warped[..., 3] > 127
    if union is not None:
        u_mask, ux0, uy0 = union
        u_mask[y0 - uy0:y1 - uy0, x0 - ux0:x1 - ux0] |= covered
    a, b, e = face.inv_depth
    inv_z = (a * np.arange(x0, x1, dtype=np.float32)[None, :] + (b * np.arange(y0, y1, dtype=np.float32) + e)[:, None])
    zbuf, ids = target.inv_depth[y0:y1, x0:x1], target.ids[y0:y1, x0:x1]
    # nothing standing on a flat ground is hidden by it: the ground loses every test (this
    # also keeps the pixels just past a face's bottom edge, where its plane dips below ground)
    drawn = covered & ((inv_z > zbuf) | (ids == GROUND_ID) | (ids == SKY_ID))
    colour = cv2.transform(warped, colour_transform(face.gain, face.fog, face.haze, tex.shape[2]))
    np.copyto(target.image[y0:y1, x0:x1], colour, where=drawn[..., None])
    np.copyto(zbuf, inv_z, where=drawn)
    np.copyto(ids, body_id, where=drawn)
