"""Top-down ground texture of a scene: asphalt roads with lane markings, kerbs, sidewalks, grass.

Drawn once per scene on a regular grid in ``map`` (texel (i, j) is centred at
x = x0 + (i + 1/2) r, y = y1 - (j + 1/2) r, r the texel size in m) and mip-mapped; the renderer
warps it into each view through the ground homography. Roads come from the bundled road
network (``v2i.sim.maps.road_network``): lane polygons are asphalt, boundary kinds become paint
(dashed / solid / double yellow centre line / edge line), stop lines and zebra crossings come
from the signals. Without a network the ground is one paved plaza.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import cv2
import numpy as np

from v2i.sim.maps.road_network import CENTRE, DASHED, EDGE, SOLID, RoadNetwork, lane_bounds
from v2i.sim.textures import mip_levels, smooth_noise

ASPHALT, SIDEWALK, KERB, GRASS, GRAVEL = (72, 73, 76), (150, 152, 150), (185, 185, 182), (60, 118, 84), (110, 125, 135)
WHITE, YELLOW = (228, 230, 230), (40, 185, 215)
MATERIAL_GRAIN = np.array([9.0, 7.0, 7.0, 14.0, 12.0], np.float32)  # asphalt, sidewalk, kerb, grass, gravel
SIDEWALK_M, KERB_M, SHOULDER_M = 3.5, 0.25, 1.2
COARSE_M = 0.5  # grid of the distance-to-road transform
FOG_M = 350.0  # fog: f = 1 - exp(-depth / FOG_M)
FAR_M = 20000.0  # ground farther than this is sky
HAZE, ZENITH = (212, 204, 196), (205, 150, 95)  # BGR sky at the horizon and high up


@dataclass(frozen=True)
class GroundRaster:
    """Mip levels of the ground (each (H_L, W_L, 3) uint8 BGR) and their placement in map."""

    levels: tuple[np.ndarray, ...]
    x0_m: float
    y1_m: float
    res_m: float
    outside_bgr: tuple[float, float, float]

    def level_to_map(self, level: int) -> np.ndarray:
        """A (3, 3): level-L texel (i, j, 1) -> map (x, y, 1); r = res 2^L,
        x = x0 + (i + 1/2) r, y = y1 - (j + 1/2) r."""
        r = self.res_m * 2.0**level
        return np.array([[r, 0.0, self.x0_m + 0.5 * r], [0.0, -r, self.y1_m - 0.5 * r], [0.0, 0.0, 1.0]])


def choose_resolution(extent_m, max_texels: float = 12e6, min_res_m: float = 0.06) -> float:
    """Texel size (m): as fine as ``min_res_m`` while the raster stays under ``max_texels`` and
    each side under 32000 texels (OpenCV's warps index sources with 16-bit integers)."""
    xmin, ymin, xmax, ymax = extent_m
    side = max(xmax - xmin, ymax - ymin) / 32000.0
    return max(min_res_m, side, float(np.sqrt((xmax - xmin) * (ymax - ymin) / max_texels)))


def _to_px(xy: np.ndarray, x0: float, y1: float, res: float, shift: int) -> np.ndarray:
    """Map points (K, 2) -> fixed-point texel coordinates for cv2 drawing with ``shift`` bits."""
    ij = np.column_stack([(xy[:, 0] - x0) / res - 0.5, (y1 - xy[:, 1]) / res - 0.5])
    return np.round(ij * (1 << shift)).astype(np.int32)


def _dashes(line: np.ndarray, on_m: float, off_m: float) -> list[np.ndarray]:
    """Pieces (each (K, 2)) of a polyline painted on for ``on_m``, off for ``off_m``, from its start."""
    seg = np.hypot(*np.diff(line, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    starts = np.arange(0.0, cum[-1], on_m + off_m)
    pieces = []
    for a in starts:
        b = min(a + on_m, cum[-1])
        inner = line[(cum > a) & (cum < b)]
        ends = [np.array([np.interp(s, cum, line[:, 0]), np.interp(s, cum, line[:, 1])]) for s in (a, b)]
        pieces.append(np.vstack([ends[0], inner, ends[1]]))
    return pieces


def _paint_lines(network: RoadNetwork, urban: bool) -> list[tuple[list[np.ndarray], tuple, float]]:
    """(polylines, colour, width m) of every painted boundary line of the network."""
    on, off = (3.0, 6.0) if urban else (6.0, 12.0)
    out = []
    for lane in network.lanes:
        for side, kind in ((0, lane.left), (1, lane.right)):
            line = lane_bounds(lane)[side]
            if kind == DASHED:
                out.append((_dashes(line, on, off), WHITE, 0.15))
            elif kind in (SOLID, EDGE):
                out.append(([line], WHITE, 0.15 if kind == SOLID else 0.2))
            elif kind == CENTRE:  # double yellow: two lines 0.12 m either side of the boundary
                pair = [lane_bounds(replace(lane, width_m=lane.width_m + d))[side] for d in (-0.24, 0.24)]
                out.append((pair, YELLOW, 0.1))
    return out


def _crossings(network: RoadNetwork) -> list[np.ndarray]:
    """Stop line bars and zebra stripes, each a (4, 2) map polygon.

    A signal's stop line runs across its approach; travel is its left normal. The crossing
    spans the whole road (the approach's width again to the left) from 0.5 to 2.5 m past it.
    """
    polys = []
    for sig in network.signals:
        a, b = sig.stop_line
        along = (b - a) / np.linalg.norm(b - a)
        travel = np.array([-along[1], along[0]])
        polys.append(np.array([a, b, b + 0.4 * travel, a + 0.4 * travel]) - 0.2 * travel)
        start = a - (b - a)
        for s in np.arange(0.3, 2 * np.linalg.norm(b - a) - 0.3, 1.0):
            p = start + s * along + 0.5 * travel
            polys.append(np.array([p, p + 0.5 * along, p + 0.5 * along + 2.0 * travel, p + 2.0 * travel]))
    return polys


def _materials(network: RoadNetwork | None, shape: tuple[int, int], x0, y1, res) -> np.ndarray:
    """Material index (H, W) uint8: 0 asphalt, 1 sidewalk, 2 kerb, 3 grass, 4 gravel shoulder."""
    h, w = shape
    if network is None:
        return np.zeros(shape, np.uint8)
    urban = any(lane.location == "urban" for lane in network.lanes)
    polys = [np.vstack([left, right[::-1]]) for left, right in (lane_bounds(lane) for lane in network.lanes)]
    ch, cw = int(np.ceil(h * res / COARSE_M)), int(np.ceil(w * res / COARSE_M))
    road = np.zeros(shape, np.uint8)
    coarse = np.full((ch, cw), 255, np.uint8)
    for p in polys:  # one call per polygon: a single fillPoly of overlapping polygons XORs them
        cv2.fillPoly(road, [_to_px(p, x0, y1, res, 3)], 1, cv2.LINE_8, 3)
        cv2.fillPoly(coarse, [_to_px(p, x0, y1, COARSE_M, 3)], 0, cv2.LINE_8, 3)
    # distance to the road on a coarse grid, upsampled: d (m) = distanceTransform(not road) * coarse texel
    dist = cv2.distanceTransform(coarse, cv2.DIST_L2, 5) * COARSE_M
    dist = cv2.resize(dist, (round(cw * COARSE_M / res), round(ch * COARSE_M / res)))[:h, :w]
    dist = np.pad(dist, ((0, h - dist.shape[0]), (0, w - dist.shape[1])), mode="edge")
    near, far = (SIDEWALK_M, 1) if urban else (SHOULDER_M, 4)
    mat = np.where(dist < KERB_M + 0.5 * COARSE_M, 2, np.where(dist < near + 0.5 * COARSE_M, far, 3)).astype(np.uint8)
    mat[road > 0] = 0
    return mat


def build_ground(network: RoadNetwork | None, extent_m, rng: np.random.Generator, res_m: float) -> GroundRaster:
    """The ground raster over ``extent_m`` (xmin, ymin, xmax, ymax) at ``res_m`` m per texel."""
    xmin, ymin, xmax, ymax = extent_m
    w, h = int(np.ceil((xmax - xmin) / res_m)), int(np.ceil((ymax - ymin) / res_m))
    x0, y1 = xmin, ymax
    mat = _materials(network, (h, w), x0, y1, res_m)
    palette = np.array([ASPHALT, SIDEWALK, KERB, GRASS, GRAVEL], np.uint8)
    img = palette[mat]
    if network is not None:
        urban = any(lane.location == "urban" for lane in network.lanes)
        for lines, colour, width in _paint_lines(network, urban):
            thick = max(round(width / res_m), 1)
            cv2.polylines(img, [_to_px(p, x0, y1, res_m, 3) for p in lines], False, colour, thick, cv2.LINE_AA, 3)
        cv2.fillPoly(img, [_to_px(p, x0, y1, res_m, 3) for p in _crossings(network)], WHITE, cv2.LINE_AA, 3)
        _sidewalk_joints(img, mat, x0, y1, res_m)
    _grain(img, mat, rng, res_m)
    outside = tuple(float(c) for c in (GRASS if network is not None else ASPHALT))
    return GroundRaster(mip_levels(img, 16), x0, y1, res_m, outside)


def _sidewalk_joints(img: np.ndarray, mat: np.ndarray, x0: float, y1: float, res: float, tile_m: float = 1.5) -> None:
    """Darken the joints of square paving slabs on sidewalk texels (in place)."""
    x = x0 + (np.arange(img.shape[1]) + 0.5) * res
    y = y1 - (np.arange(img.shape[0]) + 0.5) * res
    jx, jy = np.mod(x, tile_m) < max(res, 0.04), np.mod(y, tile_m) < max(res, 0.04)
    joint = (jy[:, None] | jx[None, :]) & (mat == 1)
    img[joint] = (np.asarray(SIDEWALK) * 0.75).astype(np.uint8)


def _grain(img: np.ndarray, mat: np.ndarray, rng: np.random.Generator, res: float, rows: int = 512) -> None:
    """Add texture in place: per-texel grain and 2 m / 8 m blotches, scaled by material."""
    h, w = mat.shape
    blotch = (smooth_noise(rng, (h, w), 2.0 / res) * 0.6 + smooth_noise(rng, (h, w), 8.0 / res)).astype(np.float32)
    for r0 in range(0, h, rows):
        r1 = min(r0 + rows, h)
        amp = MATERIAL_GRAIN[mat[r0:r1]]
        delta = (rng.standard_normal((r1 - r0, w), dtype=np.float32) + blotch[r0:r1]) * amp
        chunk = img[r0:r1].astype(np.float32) + delta[..., None]
        img[r0:r1] = np.clip(chunk, 0, 255).astype(np.uint8)


def ground_view(layers: list[GroundRaster], K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int,
                height: int) -> tuple[np.ndarray, np.ndarray]:
    """Ground and sky as an ideal camera (K, R, t) of ``width`` x ``height`` sees them:
    image (H, W, 3) uint8 and inverse depth (H, W) float32 (0 for sky).

    Map ground -> pixel: H_g = K [r1 r2 t] (r_i the columns of R). The ground plane z = 0 has
    camera-frame normal r3 through t, so 1 / z_c = (r3^T K^-1 [u, v, 1]^T) / (r3 . t), > 0 where
    the ray meets the ground ahead. ``layers`` go from the coarsest (covering everything) to
    finer ones over smaller areas, each drawn over the previous where it lies and is finer
    than it; each row is sampled from the mip level of its median footprint:
    sqrt|det J| of H_g^-1 = sqrt|det M / (m_3 . p)^3| m per pixel.
    """
    from v2i.sim.raster import inverse_depth_plane

    Hg = K @ np.column_stack([R[:, 0], R[:, 1], t])
    a, b, e = inverse_depth_plane(np.linalg.inv(K), R[:, 2], t)
    u, v = np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32)
    inv_z = a * u[None, :] + (b * v + e)[:, None]
    inv_z = np.where(inv_z > 1.0 / FAR_M, inv_z, 0.0).astype(np.float32)
    M = np.linalg.inv(Hg)
    cols = np.linspace(0, width - 1, 9)
    w_pix = M[2, 0] * cols[None, :] + M[2, 1] * v[:, None] + M[2, 2]
    with np.errstate(divide="ignore"):  # w = 0 on the horizon row
        metres = np.sqrt(np.abs(np.linalg.det(M) / w_pix**3))
    hit = inv_z[:, np.round(cols).astype(int)] > 0
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows (sky) stay NaN
        row_m = np.nanmedian(np.where(hit, metres, np.nan), axis=1)
    image = np.zeros((height, width, 3), np.uint8)
    for k, layer in enumerate(layers):
        # a finer layer only where the coarser one would be magnified (its texels > 1.5 px)
        use = np.isfinite(row_m) & ((row_m < 1.5 * layers[k - 1].res_m) if k else True)
        _warp_rows(image, layer, Hg, row_m, use, first=k == 0)
    return sky_and_haze(K, R, t, width, height, image, inv_z), inv_z


def _warp_rows(image: np.ndarray, layer: GroundRaster, Hg: np.ndarray, row_m: np.ndarray, use: np.ndarray,
               first: bool) -> None:
    """Warp ``layer`` into the rows ``use`` of ``image``, rows of one mip level at a time; the
    first layer fills its outside with its outside colour, later ones leave it untouched."""
    level = np.full(len(row_m), -1)
    # level = floor(log2(texels per pixel) + 0.6), clipped to the pyramid
    level[use] = np.clip(np.floor(np.log2(row_m[use] / layer.res_m) + 0.6), 0, len(layer.levels) - 1)
    rows = np.flatnonzero(level >= 0)
    if len(rows) == 0:
        return
    border = cv2.BORDER_CONSTANT if first else cv2.BORDER_TRANSPARENT
    for band in np.split(rows, np.flatnonzero((np.diff(level[rows]) != 0) | (np.diff(rows) > 1)) + 1):
        v0, v1, lv = int(band[0]), int(band[-1]) + 1, int(level[band[0]])
        shift = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -v0], [0.0, 0.0, 1.0]])
        cv2.warpPerspective(layer.levels[lv], shift @ Hg @ layer.level_to_map(lv), (image.shape[1], v1 - v0),
                            dst=image[v0:v1], flags=cv2.INTER_LINEAR, borderMode=border,
                            borderValue=layer.outside_bgr)


def fog_fraction(depth_m: np.ndarray | float):
    """Fraction of haze: f = 1 - exp(-depth / FOG_M)."""
    return 1.0 - np.exp(-np.asarray(depth_m, dtype=np.float32) / FOG_M)


def sky_and_haze(K, R, t, width: int, height: int, ground: np.ndarray, inv_depth: np.ndarray,
                 step_px: int = 8) -> np.ndarray:
    """Ground faded toward HAZE with depth (fog), sky where no ground.

    Sky colour from HAZE at the horizon to ZENITH with the ray's elevation, sin(el) = d_z / |d|,
    d = R^T K^-1 [u, v, 1]^T (HAZE below the horizon, so one "far" image serves as sky and as
    fog colour); out = (1 - f) ground + f far, f = 1 - exp(-depth / FOG_M), 1 for sky. Both
    are smooth, so they are evaluated every ``step_px`` pixels and interpolated.
    """
    from v2i.sim.raster import inverse_depth_plane

    u = np.arange(0, width + step_px, step_px, dtype=np.float32)
    v = np.arange(0, height + step_px, step_px, dtype=np.float32)
    M = (R.T @ np.linalg.inv(K)).astype(np.float32)
    rays = M[None, None, :, 0] * u[None, :, None] + M[None, None, :, 1] * v[:, None, None] + M[:, 2]
    k = np.clip(rays[..., 2] / np.linalg.norm(rays, axis=-1) / 0.35, 0.0, 1.0) ** 0.7
    haze, zenith = np.asarray(HAZE, np.float32), np.asarray(ZENITH, np.float32)
    far_small = haze + k[..., None] * (zenith - haze)
    a, b, e = inverse_depth_plane(np.linalg.inv(K), R[:, 2], t)
    inv_z = a * u[None, :] + (b * v + e)[:, None]
    with np.errstate(divide="ignore"):
        fog_small = np.where(inv_z > 0, fog_fraction(1.0 / np.maximum(inv_z, 1e-9)), 1.0).astype(np.float32)
    size = (len(u) * step_px, len(v) * step_px)
    far = cv2.resize(np.clip(far_small, 0, 255).astype(np.uint8), size)[:height, :width]
    fog = cv2.resize(fog_small, size)[:height, :width]
    np.putmask(fog, inv_depth <= 0, 1.0)
    return cv2.blendLinear(ground, far, 1.0 - fog, fog)
