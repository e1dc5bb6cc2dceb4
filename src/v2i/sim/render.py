"""Camera images of the simulated world, with exact box labels (numpy + OpenCV, no GPU).

``SceneRenderer(world, seed).render(camera, t_s)`` draws what ``camera`` (``v2i.sim.camera``) sees
at scenario time t_s: sky, a textured ground (roads, markings, sidewalks from the road
network; ``v2i.sim.ground_raster``), buildings extruded from their footprints with window facades,
and every actor (and the ego, id 0) as a textured, sun-shaded 3-D box (``v2i.sim.textures``).
Occlusion is a per-pixel inverse-depth test (``v2i.sim.raster``); faces are backface-culled and
clipped to the view frustum in camera coordinates. A distorted camera is rendered on an ideal
canvas that covers its field of view, then resampled with ``cv2.remap``.

Labels: for every body with a pixel in the image, its id, class, the box of its projected
3-D corners (clipped to the image), its visible fraction (pixels it shows / pixels its
silhouette covers with nothing in front, both inside the image) and its horizontal range.

Static parts (sky, ground, buildings) are drawn once per camera pose and reused, so a fixed
RSU camera pays only for the actors each frame. With ``rng`` the frame gets a random
exposure, sometimes motion or defocus blur, and Gaussian sensor noise; without, it is clean
and deterministic.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.stats

from v2i.core.objects import ObjectArray

from v2i.sim import raster
from v2i.sim.body_textures import FIGURES, body_parts
from v2i.sim.camera import PinholeCamera
from v2i.sim.ground_raster import (
    HAZE,
    GroundRaster,
    build_ground,
    choose_resolution,
    fog_fraction,
    ground_view,
)
from v2i.sim.maps.road_network import road_network
from v2i.sim.scenario import bundled_scenarios
from v2i.sim.scene_faces import (
    WorldFace,
    body_faces,
    box_corners,
    building_faces,
    detail_extent,
    scene_extent,
)
from v2i.sim.world import World

AMBIENT, DIFFUSE = 0.6, 0.45  # face gain = AMBIENT + DIFFUSE max(0, n . sun)
SUN_ELEVATION_RAD = np.deg2rad(50.0)
SHADOW_GAIN = 0.6
CACHE = 6


@dataclass(frozen=True)
class BoxLabels:
    """N bodies in a frame: ids (N,) int64 (ego 0), cls (N,) int64 ObjectClass, xyxy (N, 4) px,
    visible (N,) fraction in [0, 1], range_m (N,) horizontal camera-to-centre distance."""

    ids: np.ndarray
    cls: np.ndarray
    xyxy: np.ndarray
    visible: np.ndarray
    range_m: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class RenderedFrame:
    image: np.ndarray  # (H, W, 3) uint8 BGR
    labels: BoxLabels
    t_s: float | None


@dataclass(frozen=True)
class _Canvas:
    """The ideal pinhole image a camera is rendered on: intrinsics ``K`` of a ``width`` x
    ``height`` canvas, pose R, t; for a distorted camera, ``maps`` (output px -> canvas px,
    two (H, W) float32) and ``footprint`` (canvas pixels that land in the output)."""

    camera: PinholeCamera
    K: np.ndarray
    width: int
    height: int
    maps: tuple | None
    footprint: np.ndarray | None

    def __post_init__(self) -> None:
        object.__setattr__(self, "K_inv", np.linalg.inv(self.K))
        object.__setattr__(self, "planes", raster.frustum_planes(self.K, self.width, self.height))

    @property
    def R(self) -> np.ndarray:
        return self.camera.R

    @property
    def t(self) -> np.ndarray:
        return self.camera.t


def _distorted_canvas(camera: PinholeCamera) -> tuple[np.ndarray, int, int, tuple, np.ndarray]:
    """Canvas intrinsics, size, remap maps and footprint covering a distorted camera's view."""
    w, h = camera.width, camera.height
    s = np.linspace(-0.5, 1.0, 65)
    edge = np.concatenate([np.column_stack([s * w, np.full_like(s, v)]) for v in (-0.5, h - 0.5)]
                          + [np.column_stack([np.full_like(s, u), s * h]) for u in (-0.5, w - 0.5)])
    ideal = camera.undistort(edge)
    lo = np.maximum(np.floor(ideal.min(axis=0)) - 2, [-w, -h])
    hi = np.minimum(np.ceil(ideal.max(axis=0)) + 2, [2 * w, 2 * h])
    K = camera.K.copy()
    K[:2, 2] -= lo
    cw, ch = int(hi[0] - lo[0]), int(hi[1] - lo[1])
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    src = cv2.undistortPoints(np.column_stack([u.ravel(), v.ravel()]).reshape(-1, 1, 2), camera.K, camera.dist,
                              P=camera.K, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-6))
    src = src.reshape(h, w, 2) - lo
    cu, cv_ = np.meshgrid(np.arange(cw, dtype=float), np.arange(ch, dtype=float))
    rays = np.column_stack([(cu.ravel() - K[0, 2]) / K[0, 0], (cv_.ravel() - K[1, 2]) / K[1, 1], np.ones(cu.size)])
    out, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), camera.K, camera.dist)
    out = out.reshape(ch, cw, 2)
    inside = (out[..., 0] >= -0.5) & (out[..., 0] < w - 0.5) & (out[..., 1] >= -0.5) & (out[..., 1] < h - 0.5)
    return K, cw, ch, (src[..., 0].astype(np.float32), src[..., 1].astype(np.float32)), inside


def _sun(seed: int) -> np.ndarray:
    """Unit vector (3,) toward the sun: SUN_ELEVATION_RAD up, azimuth from the scene seed."""
    az = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2,))).uniform(0, 2 * np.pi)
    return np.array([np.cos(SUN_ELEVATION_RAD) * np.cos(az), np.cos(SUN_ELEVATION_RAD) * np.sin(az),
                     np.sin(SUN_ELEVATION_RAD)])


def _network(world: World):
    name = world.scenario.name
    if name not in bundled_scenarios():
        return None
    try:
        return road_network(name)
    except ValueError:
        return None


def _ground_layers(world: World, rng_coarse, rng_fine, res_m: float | None) -> list[GroundRaster]:
    """The ground as a coarse raster of the whole scene (<= 3 M texels) under a detailed one
    around the RSU and the ego's path (<= 12 M texels, >= 0.06 m); one raster if that covers it all."""
    network = _network(world)
    whole, near = scene_extent(world), detail_extent(world)
    fine_res = res_m or choose_resolution(near)
    coarse_res = choose_resolution(whole, max_texels=3e6, min_res_m=fine_res)
    if coarse_res <= 1.5 * fine_res:  # the whole scene fits the detail budget
        return [build_ground(network, whole, rng_fine, res_m or choose_resolution(whole))]
    return [build_ground(network, whole, rng_coarse, coarse_res), build_ground(network, near, rng_fine, fine_res)]


class SceneRenderer:
    """Renders a ``World`` through any ``PinholeCamera``; textures fixed by ``seed``."""

    def __init__(self, world: World, seed: int = 0, ground_res_m: float | None = None):
        """``ground_res_m``: texel size of the detailed ground (default: from a texel budget)."""
        self.world, self.seed = world, int(seed)
        self.sun = _sun(self.seed)
        self.ground = _ground_layers(world, self._rng(0), self._rng(4), ground_res_m)
        self.buildings: list[WorldFace] = building_faces(world, self.seed)
        self._textures: OrderedDict = OrderedDict()
        self._backgrounds: OrderedDict = OrderedDict()
        self._intrinsics: OrderedDict = OrderedDict()
        self.ego_cls = int(world.scenario.ego.cls)

    def _rng(self, *key: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=key))

    # ------------------------------------------------------------------ public
    def render(self, camera: PinholeCamera, t_s: float, rng: np.random.Generator | None = None,
               hide_ego: bool = False) -> RenderedFrame:
        """The frame ``camera`` takes at scenario time ``t_s`` (s): actors and, unless ``hide_ego``, the ego."""
        actors = self.world.actors_at(t_s)
        ids, cls, xy = actors.ids, actors.cls, actors.xy
        z_bottom, lwh, yaw = actors.z - actors.lwh[:, 2] / 2.0, actors.lwh, actors.yaw
        if not hide_ego and self.world.ego_name is not None:  # the site view has no ego
            ego = self.world.ego_at(t_s)
            ids, cls = np.append(ids, 0), np.append(cls, self.ego_cls)
            xy, z_bottom = np.vstack([xy, [ego.x, ego.y]]), np.append(z_bottom, 0.0)
            lwh, yaw = np.vstack([lwh, self.world.ego_size]), np.append(yaw, ego.yaw)
        image, labels = self._render(camera, (ids, cls, xy, z_bottom, lwh, yaw), rng)
        return RenderedFrame(image, labels, float(t_s))

    def render_bodies(self, camera: PinholeCamera, bodies: ObjectArray,
                      rng: np.random.Generator | None = None) -> RenderedFrame:
        """The static scene with any ``bodies`` (map; ``z`` the box centre height; ids >= 0) instead of the actors."""
        if len(bodies) and np.min(bodies.ids) < 0:
            raise ValueError("body ids must be >= 0 (negative ids mark sky, ground and buildings)")
        z_bottom = np.asarray(bodies.z, float) - bodies.lwh[:, 2] / 2.0
        image, labels = self._render(camera, (bodies.ids, bodies.cls, bodies.xy, z_bottom, bodies.lwh, bodies.yaw), rng)
        return RenderedFrame(image, labels, None)

    # ------------------------------------------------------------------ frame
    def _render(self, camera: PinholeCamera, bodies, rng) -> tuple[np.ndarray, BoxLabels]:
        canvas = self._canvas(camera)
        target = self._background(canvas).copy()
        ids, cls, xy, z_bottom, lwh, yaw = bodies
        order = np.argsort(-np.hypot(*(np.asarray(xy) - camera.centre[:2]).T))  # far to near: fewer overdraws
        self._shadows(target, canvas, xy, lwh * np.where(np.isin(cls, FIGURES), 0.5, 1.0)[:, None], yaw)
        drawn = []
        for k in order:
            faces = body_faces(xy[k], float(z_bottom[k]), float(yaw[k]), self._body_parts(ids[k], cls[k], lwh[k]),
                               camera.centre[:2])
            area = self._draw_body(target, canvas, faces, int(ids[k]))
            if area:
                drawn.append((k, area, self._xyxy(canvas, box_corners(xy[k], float(z_bottom[k]), lwh[k], float(yaw[k])))))
        labels = self._labels(target, canvas, drawn, ids, cls, xy)
        image = target.image if canvas.maps is None else cv2.remap(target.image, *canvas.maps, cv2.INTER_LINEAR,
                                                                     borderMode=cv2.BORDER_REPLICATE)
        return (image if rng is None else sensor_effects(image, rng)), labels

    def _draw_body(self, target: raster.Target, canvas: _Canvas, faces: list[WorldFace], body_id: int) -> int:
        """Draw one body; the pixel count of its unoccluded silhouette in the image (0: not in view)."""
        ready = [f for f in (self._face(canvas, wf) for wf in faces) if f is not None]
        if not ready:
            return 0
        box = raster.bbox_of(np.concatenate([f.uv for f in ready]), canvas.width, canvas.height)
        if box is None:
            return 0
        x0, y0, x1, y1 = box
        union = np.zeros((y1 - y0, x1 - x0), bool)
        for face in ready:
            raster.draw_face(target, face, body_id, (union, x0, y0))
        if canvas.footprint is not None:
            union &= canvas.footprint[y0:y1, x0:x1]
        return int(np.count_nonzero(union))

    def _xyxy(self, canvas: _Canvas, corners: dict) -> np.ndarray:
        """Box (4,) x0, y0, x1, y1 of the full 3-D box in output pixels, clipped to the image: its
        faces clipped to the view frustum, projected (through the lens: edges sampled, as
        distortion bends them)."""
        cam = canvas.camera
        polys = [raster.clip_polygon(p @ cam.R.T + cam.t, canvas.planes) for p in corners.values()]
        polys = [p for p in polys if len(p)]
        if not polys:
            return np.zeros(4)
        if canvas.maps is None:
            uv = raster.project_ideal(cam.K, np.concatenate(polys))
        else:
            s = np.linspace(0.0, 1.0, 8, endpoint=False)[:, None, None]
            pts = np.concatenate([(p[None] + s * (np.roll(p, -1, axis=0) - p)[None]).reshape(-1, 3) for p in polys])
            uv, _ = cv2.projectPoints(pts / pts[:, 2:3], np.zeros(3), np.zeros(3), cam.K, cam.dist)
            uv = uv.reshape(-1, 2)
        size = [cam.width, cam.height]
        return np.concatenate([np.clip(uv.min(axis=0), 0, size), np.clip(uv.max(axis=0), 0, size)])

    def _face(self, canvas: _Canvas, wf: WorldFace):
        """The ``raster.Face`` of a world face in this canvas, or None (back-facing or out of view)."""
        C = canvas.camera.centre
        if np.dot(wf.normal, C - wf.polygon[0]) <= 0:  # backface: the camera is behind its plane
            return None
        R, t = canvas.R, canvas.t
        poly_c = raster.clip_polygon(wf.polygon @ R.T + t, canvas.planes)
        if len(poly_c) < 3:
            return None
        uv = raster.project_ideal(canvas.K, poly_c)
        plane = raster.inverse_depth_plane(canvas.K_inv, R @ wf.normal, poly_c[0])
        H = raster.texel_homography(canvas.K, R, t, wf.origin, wf.e_s, wf.e_t)
        gain = AMBIENT + DIFFUSE * max(0.0, float(wf.normal @ self.sun))
        fog = float(fog_fraction(poly_c[:, 2].mean()))
        return raster.Face(uv, plane, H, wf.levels, gain, fog, HAZE)

    def _labels(self, target, canvas: _Canvas, drawn: list, ids, cls, xy) -> BoxLabels:
        if not drawn:
            return BoxLabels(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros(0), np.zeros(0))
        idx = np.array([d[0] for d in drawn])
        area = np.array([d[1] for d in drawn], float)
        xyxy = np.array([d[2] for d in drawn], float)
        shown = target.ids if canvas.footprint is None else np.where(canvas.footprint, target.ids, raster.SKY_ID)
        body_ids = np.asarray(ids, np.int64)[idx]
        counts = _pixel_counts(shown, body_ids)
        range_m = np.hypot(*(np.asarray(xy, float)[idx] - canvas.camera.centre[:2]).T)
        order = np.argsort(body_ids, kind="stable")
        return BoxLabels(body_ids[order], np.asarray(cls, np.int64)[idx][order], xyxy[order],
                         np.clip(counts / area, 0.0, 1.0)[order], range_m[order])

    # ------------------------------------------------------------------ static parts
    def _canvas(self, camera: PinholeCamera) -> _Canvas:
        if not camera.distorted:
            return _Canvas(camera, camera.K, camera.width, camera.height, None, None)
        key = (camera.K.tobytes(), camera.dist.tobytes(), camera.width, camera.height)
        if key not in self._intrinsics:
            self._intrinsics[key] = _distorted_canvas(camera)
            while len(self._intrinsics) > CACHE:
                self._intrinsics.popitem(last=False)
        K, w, h, maps, footprint = self._intrinsics[key]
        return _Canvas(camera, K, w, h, maps, footprint)

    def _background(self, canvas: _Canvas) -> raster.Target:
        cam = canvas.camera
        key = (cam.K.tobytes(), cam.dist.tobytes(), cam.R.tobytes(), cam.t.tobytes(), cam.width, cam.height)
        if key in self._backgrounds:
            self._backgrounds.move_to_end(key)
            return self._backgrounds[key]
        image, inv_depth = ground_view(self.ground, canvas.K, canvas.R, canvas.t, canvas.width, canvas.height)
        target = raster.Target(image, inv_depth, np.where(inv_depth > 0, raster.GROUND_ID, raster.SKY_ID).astype(np.int32))
        for wf in self.buildings:
            got = self._face(canvas, wf)
            if got is not None:
                raster.draw_face(target, got, raster.BUILDING_ID)
        self._backgrounds[key] = target
        while len(self._backgrounds) > CACHE:
            self._backgrounds.popitem(last=False)
        return target

    def _body_parts(self, body_id, cls, lwh) -> list:
        """Textured part boxes of a body, fixed by (scene seed, id, class); cached."""
        key = (int(body_id), int(cls), tuple(np.round(np.asarray(lwh, float), 2)))
        if key not in self._textures:
            self._textures[key] = body_parts(self._rng(3, int(body_id) & 0xFFFFFFFF, int(cls)), int(cls), lwh)
            while len(self._textures) > 512:
                self._textures.popitem(last=False)
        return self._textures[key]

    def _shadows(self, target: raster.Target, canvas: _Canvas, xy, lwh, yaw) -> None:
        """Darken the ground under and behind each body (hull of its footprint and of its top
        corners projected along the sun onto z = 0: offset = -h cot(elev) * sun_xy)."""
        planes = canvas.planes
        sun_xy = self.sun[:2] / np.hypot(*self.sun[:2])
        for k in range(len(xy)):
            foot = _footprint(xy[k], lwh[k, 0] + 0.2, lwh[k, 1] + 0.2, yaw[k])
            cast = foot - sun_xy * lwh[k, 2] / np.tan(SUN_ELEVATION_RAD) * 0.6
            hull = cv2.convexHull(np.vstack([foot, cast]).astype(np.float32)).reshape(-1, 2).astype(float)
            poly_c = raster.clip_polygon(np.column_stack([hull, np.full(len(hull), 0.01)]) @ canvas.R.T + canvas.t, planes)
            if len(poly_c) < 3:
                continue
            uv = raster.project_ideal(canvas.K, poly_c)
            box = raster.bbox_of(uv, canvas.width, canvas.height)
            if box is None:
                continue
            x0, y0, x1, y1 = box
            mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
            cv2.fillPoly(mask, [np.round((uv - (x0, y0)) * 16).astype(np.int32)], 1, cv2.LINE_8, 4)
            dark = mask.view(bool) & (target.ids[y0:y1, x0:x1] == raster.GROUND_ID)
            region = target.image[y0:y1, x0:x1]
            np.copyto(region, (region * SHADOW_GAIN).astype(np.uint8), where=dark[..., None])


def _pixel_counts(ids: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """How many pixels of the id buffer ``ids`` carry each of the ``wanted`` (K,) ids, (K,) float."""
    if wanted.max() < 1 << 20:  # ids from BUILDING_ID = -3 up to a small bound: one bincount
        counts = np.bincount((ids.ravel() - raster.BUILDING_ID).astype(np.int64), minlength=int(wanted.max()) + 4)
        return counts[wanted - raster.BUILDING_ID].astype(float)
    values, counts = np.unique(ids, return_counts=True)
    return np.array([counts[values == i].sum() for i in wanted], float)


def _footprint(xy, l: float, w: float, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([[l, w], [-l, w], [-l, -w], [l, -w]]) / 2.0
    return np.asarray(xy, float) + local @ np.array([[c, s], [-s, c]])


def sensor_effects(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A camera's frame-to-frame imperfections on a clean image (H, W, 3) uint8:
    exposure I' = g I + b (g = exp(N(0, 0.12)), b ~ N(0, 6)); motion blur (20 %: a 3-6 px line
    kernel at a random angle) or defocus (15 %: Gaussian, sigma 0.5-1.2 px); then Gaussian noise
    with sigma ~ U(1.5, 5) levels."""
    img = image.astype(np.float32) * np.float32(np.exp(rng.normal(0.0, 0.12))) + np.float32(rng.normal(0.0, 6.0))
    kind = rng.random()
    if kind < 0.2:
        n = int(rng.integers(3, 7))
        kernel = np.zeros((n, n), np.float32)
        angle = rng.uniform(0, np.pi)
        c = (n - 1) / 2
        d = np.array([np.cos(angle), np.sin(angle)]) * c
        cv2.line(kernel, (round(c - d[0]), round(c - d[1])), (round(c + d[0]), round(c + d[1])), 1.0)
        img = cv2.filter2D(img, -1, kernel / kernel.sum())
    elif kind < 0.35:
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.5, 1.2))
    # Gaussian noise from random bytes through the normal quantile table (8x faster than
    # standard_normal for a frame; 256 levels out to +-2.9 sigma)
    noise = _NORMAL_QUANTILES[np.frombuffer(rng.bytes(img.size), np.uint8)].reshape(img.shape)
    img += noise * np.float32(rng.uniform(1.5, 5.0))
    return np.clip(img, 0, 255).astype(np.uint8)


_NORMAL_QUANTILES = scipy.stats.norm.ppf((np.arange(256) + 0.5) / 256).astype(np.float32)
