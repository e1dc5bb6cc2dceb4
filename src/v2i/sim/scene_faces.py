"""The world as planar textured faces in ``map``: building walls and roofs, box bodies.

Buildings are their footprints (boxes or polygons) extruded to a height from a hash of name
and index (12-25 m); walls face outward from the counter-clockwise footprint and are cut into
pieces (``WALL_CHUNK_M``) so that the renderer picks a texture level per piece. Bodies are
boxes on the ground: five faces (the bottom is never seen from above the ground).
"""

from __future__ import annotations

import itertools
import zlib
from dataclasses import dataclass

import numpy as np

from v2i.sim.textures import FACES, facade_style, facade_texture, mip_levels, roof_texture
from v2i.sim.world import World

WALL_CHUNK_M = 8.0

# corners of each box face in the body frame as (x sign, y sign, top?) TL, TR, BR, BL seen from outside
_FACE_CORNERS = {
    "front": ((1, -1, 1), (1, 1, 1), (1, 1, 0), (1, -1, 0)),
    "back": ((-1, 1, 1), (-1, -1, 1), (-1, -1, 0), (-1, 1, 0)),
    "left": ((1, 1, 1), (-1, 1, 1), (-1, 1, 0), (1, 1, 0)),
    "right": ((-1, -1, 1), (1, -1, 1), (1, -1, 0), (-1, -1, 0)),
    "top": ((-1, 1, 1), (1, 1, 1), (1, -1, 1), (-1, -1, 1)),
}


@dataclass(frozen=True)
class WorldFace:
    """A planar face in map: polygon (K, 3), outward normal (3,), texel grid (texel (i, j)
    centred at origin + i e_s + j e_t, all (3,) m) and its texture's mip levels."""

    polygon: np.ndarray
    normal: np.ndarray
    origin: np.ndarray
    e_s: np.ndarray
    e_t: np.ndarray
    levels: tuple


def scene_extent(world: World, margin_m: float = 40.0) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) m around every path, building and the RSU, plus a margin."""
    sc = world.scenario
    pts = [np.asarray(b.trajectory.path, float) for b in [sc.ego, *sc.actors]]
    pts += [np.asarray(p, float) for p in world.building_polygons]
    pts += [np.array([[sc.rsu.position.x, sc.rsu.position.y]])]
    pts += [_box_polygon(b) for b in world.building_boxes]
    allp = np.concatenate(pts)
    lo, hi = allp.min(axis=0) - margin_m, allp.max(axis=0) + margin_m
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def detail_extent(world: World, rsu_margin_m: float = 80.0, ego_margin_m: float = 60.0) -> tuple[float, ...]:
    """(xmin, ymin, xmax, ymax) m of the ground seen up close: around the RSU and the ego's path,
    within ``scene_extent``."""
    sc = world.scenario
    ego = np.asarray(sc.ego.trajectory.path, float)
    rsu = np.array([sc.rsu.position.x, sc.rsu.position.y])
    lo = np.minimum(ego.min(axis=0) - ego_margin_m, rsu - rsu_margin_m)
    hi = np.maximum(ego.max(axis=0) + ego_margin_m, rsu + rsu_margin_m)
    xmin, ymin, xmax, ymax = scene_extent(world)
    return max(lo[0], xmin), max(lo[1], ymin), min(hi[0], xmax), min(hi[1], ymax)


def _box_polygon(box) -> np.ndarray:
    """Rotated rectangle [x, y, l, w, yaw] -> (4, 2) CCW corners."""
    x, y, l, w, yaw = box
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([[l, w], [-l, w], [-l, -w], [l, -w]]) / 2.0
    return np.array([x, y]) + local @ np.array([[c, s], [-s, c]])


def building_height_m(name: str, index: int) -> float:
    """12..25 m from a hash of the building's name and index (stable across runs)."""
    return 12.0 + 13.0 * (zlib.crc32(f"{name}:{index}".encode()) % 1000) / 1000.0


def building_faces(world: World, seed: int) -> list[WorldFace]:
    """Walls (in WALL_CHUNK_M pieces) and the roof of every building."""
    faces = []
    for index, b in enumerate(world.scenario.buildings):
        poly = _box_polygon([b.box.x, b.box.y, b.box.l, b.box.w, np.deg2rad(b.box.yaw_deg)]) if b.box else \
            np.asarray(b.polygon, float)
        if _area(poly) < 0:  # walls face outward from a CCW footprint
            poly = poly[::-1]
        height = building_height_m(b.name, index)
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(1, index)))
        style = facade_style(rng)
        for k in range(len(poly)):
            faces += _wall_faces(rng, poly[k], poly[(k + 1) % len(poly)], height, style)
        faces.append(_roof_face(rng, poly, height))
    return faces


def _area(poly: np.ndarray) -> float:
    """Signed area (m^2), positive for CCW: A = 1/2 sum (x_k y_k+1 - x_k+1 y_k)."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _wall_faces(rng, a: np.ndarray, b: np.ndarray, height: float, style: dict) -> list[WorldFace]:
    """Wall from a to b (CCW footprint edge: outward normal on its right), seen unmirrored."""
    length = float(np.hypot(*(b - a)))
    tex = facade_texture(rng, length, height, style)
    levels = mip_levels(tex)
    d = np.append((b - a) / length, 0.0)
    normal = np.array([d[1], -d[0], 0.0])
    top_left = np.array([a[0], a[1], height])
    e_s = d * length / tex.shape[1]
    e_t = np.array([0.0, 0.0, -height / tex.shape[0]])
    origin = top_left + 0.5 * e_s + 0.5 * e_t
    cuts = np.linspace(0.0, length, int(np.ceil(length / WALL_CHUNK_M)) + 1)
    out = []
    for s0, s1 in itertools.pairwise(cuts):
        p0, p1 = top_left + s0 * d, top_left + s1 * d
        poly = np.array([p0, p1, p1 - [0, 0, height], p0 - [0, 0, height]])
        out.append(WorldFace(poly, normal, origin, e_s, e_t, levels))
    return out


def _roof_face(rng, poly: np.ndarray, height: float) -> WorldFace:
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    tex = roof_texture(rng, *(hi - lo))
    e_s = np.array([(hi[0] - lo[0]) / tex.shape[1], 0.0, 0.0])
    e_t = np.array([0.0, -(hi[1] - lo[1]) / tex.shape[0], 0.0])
    origin = np.array([lo[0], hi[1], height]) + 0.5 * e_s + 0.5 * e_t
    return WorldFace(np.column_stack([poly, np.full(len(poly), height)]), np.array([0.0, 0.0, 1.0]), origin, e_s, e_t,
                     mip_levels(tex))


def box_corners(xy, z_bottom: float, lwh, yaw: float, dx_m: float = 0.0) -> dict[str, np.ndarray]:
    """Corners (4, 3) map of each face of a box (TL, TR, BR, BL seen from outside), plus its
    bottom; the box's centre is ``dx_m`` ahead of ``xy`` along ``yaw``."""
    l, w, h = (float(v) for v in lwh)
    c, s = np.cos(yaw), np.sin(yaw)
    fwd, left = np.array([c, s, 0.0]), np.array([-s, c, 0.0])
    base = np.array([xy[0], xy[1], z_bottom]) + dx_m * fwd
    out = {name: np.array([base + sx * l / 2 * fwd + sy * w / 2 * left + [0.0, 0.0, top * h]
                           for sx, sy, top in corners]) for name, corners in _FACE_CORNERS.items()}
    out["bottom"] = out["top"][::-1] - [0.0, 0.0, h]
    return out


def body_faces(xy, z_bottom: float, yaw: float, parts, view_xy) -> list[WorldFace]:
    """The faces of each part box of a body, textured: five (no bottom) for a solid part; for a
    ``billboard`` part (a figure) one vertical quad through its centre facing the viewer at
    ``view_xy`` (2,) m, showing the side of the figure that faces the viewer (a box would show
    a figure on each of two faces)."""
    c, s = np.cos(yaw), np.sin(yaw)
    fwd, left = np.array([c, s, 0.0]), np.array([-s, c, 0.0])
    normals = {"front": fwd, "back": -fwd, "left": left, "right": -left, "top": np.array([0.0, 0.0, 1.0])}
    out = []
    for part in parts:
        corners = box_corners(xy, z_bottom + part.z0_m, part.lwh, yaw, part.dx_m)
        if part.billboard:
            out.append(_billboard(xy, z_bottom + part.z0_m, yaw, part, view_xy))
            continue
        for name in FACES:
            out.append(_textured(corners[name], normals[name], part.faces[name]))
    return out


def _textured(p: np.ndarray, normal: np.ndarray, levels: tuple) -> WorldFace:
    """A face with corners p (4, 3) TL, TR, BR, BL and the texture stretched over it."""
    th, tw = levels[0].shape[:2]
    e_s, e_t = (p[1] - p[0]) / tw, (p[3] - p[0]) / th
    return WorldFace(p, normal, p[0] + 0.5 * e_s + 0.5 * e_t, e_s, e_t, levels)


def _billboard(xy, z0: float, yaw: float, part, view_xy) -> WorldFace:
    """Vertical quad through the part's centre, normal n toward the viewer (horizontal), right
    = z x n; the texture of the face whose normal is within 45 deg of n, at that face's width."""
    d = np.asarray(view_xy, float) - np.asarray(xy, float)
    az = float(np.arctan2(d[1], d[0]))
    rel = (az - yaw + np.pi) % (2 * np.pi) - np.pi  # viewer's bearing in the body frame
    name = ("front", "left", "back", "right")[int(np.floor((rel + np.pi / 4) / (np.pi / 2))) % 4]
    l, w, h = part.lwh
    half = (w if name in ("front", "back") else l) / 2
    n = np.array([np.cos(az), np.sin(az), 0.0])
    right = np.array([-n[1], n[0], 0.0])
    c = np.array([xy[0], xy[1], z0]) + part.dx_m * np.array([np.cos(yaw), np.sin(yaw), 0.0])
    up = np.array([0.0, 0.0, h])
    return _textured(np.array([c - half * right + up, c + half * right + up, c + half * right, c - half * right]),
                     n, part.faces[name])
