"""Rendered scenes for training and evaluating the image detector (``tools/train_detector.py``,
``benchmarks/detector.py``): the bundled scenarios' worlds seen from random cameras, with random
extra bodies on their roads.

Frame k of seed s draws everything from ``default_rng(SeedSequence(s, spawn_key=(k,)))``, so a
frame is the same whichever worker renders it. Per frame: a scenario, a time t, a camera

- ``rsu`` (30 %): the scenario's RSU image camera, pose jittered (yaw +-15 deg, pitch +-3 deg,
  height +-2 m, fov +-10 deg);
- ``pole`` (45 %): a pole 4-12 m high, 3-12 m beside a random lane, aimed (+-15 deg, +-2 deg)
  at a point of the lane 15-70 m ahead or behind, fov 50-100 deg;
- ``vehicle`` (25 %): a car-mounted camera on a random lane, 1.2-2 m high, pitch -2..6 deg,
  fov 60-100 deg;

20 % of cameras get one of four distorted lenses (k1 -0.25..0.04). Bodies: the world's actors at t (and
the ego) plus 3-30 random bodies of every class placed in view on the lanes (vehicles on lane
centres, pedestrians beside and across lanes), no two overlapping, none inside a building.
80 % of frames get the renderer's sensor effects (exposure, blur, noise).
"""

from __future__ import annotations

import json
import multiprocessing as mp
import time
from functools import lru_cache
from pathlib import Path

import numpy as np
import shapely

from detector_samples import INPUT_HW
from v2i.core.frames import Pose2D
from v2i.core.objects import ObjectArray
from schemas.classes import ObjectClass
from v2i.sim.camera import PinholeCamera, rsu_camera
from v2i.sim.maps.road_network import road_network
from v2i.sim.render import SceneRenderer
from v2i.sim.scenario import load_scenario
from v2i.sim.world import World

C = ObjectClass
# class: (probability, (l lo, l hi), (w lo, w hi), (h lo, h hi)) m
BODY_PRIORS = {
    C.CAR: (0.26, (3.8, 5.0), (1.65, 1.95), (1.35, 1.65)),
    C.VAN: (0.10, (4.8, 6.5), (1.9, 2.1), (1.9, 2.8)),
    C.TRUCK: (0.09, (6.5, 12.0), (2.3, 2.55), (2.8, 3.9)),
    C.BUS: (0.08, (10.0, 13.5), (2.45, 2.6), (2.9, 3.4)),
    C.PEDESTRIAN: (0.20, (0.35, 0.65), (0.35, 0.65), (1.5, 1.95)),
    C.CYCLIST: (0.15, (1.6, 1.9), (0.5, 0.7), (1.55, 1.9)),
    C.MOTORCYCLE: (0.12, (1.9, 2.3), (0.7, 0.9), (1.3, 1.6)),
}
SCENARIOS = ("red-light-runner", "dense-intersection", "highway-merge")  # pinned: same seed, same data
VIEWS = (("rsu", 0.30), ("pole", 0.45), ("vehicle", 0.25))
RENDER_SEEDS = 3  # renderer seeds (sun direction, textures) per scenario
EXTRA_ID0 = 1000  # ids of the random bodies start here
DISTORTED_SHARE = 0.2  # share of cameras with radial distortion, one of the lenses below
LENSES = ((70.0, -0.20, 0.03), (90.0, -0.12, 0.01), (100.0, -0.25, 0.05), (60.0, 0.04, 0.0))  # hfov deg, k1, k2
# (few lenses, so the renderer's per-intrinsics remap cache hits: a new one costs ~0.6 s)


@lru_cache(maxsize=None)
def scene(name: str, render_seed: int) -> tuple[World, SceneRenderer]:
    world = World(load_scenario(name))
    return world, SceneRenderer(world, seed=render_seed)


@lru_cache(maxsize=None)
def lanes(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All lane segments of a scenario: start (S, 2), direction (S, 2) unit, length (S,), lane width (S,)."""
    starts, dirs, lengths, widths = [], [], [], []
    for lane in road_network(name).lanes:
        seg = np.diff(lane.centre, axis=0)
        n = np.hypot(*seg.T)
        ok = n > 1e-6
        starts.append(lane.centre[:-1][ok]), dirs.append(seg[ok] / n[ok, None]), lengths.append(n[ok])
        widths.append(np.full(ok.sum(), lane.width_m))
    return tuple(np.concatenate(a) for a in (starts, dirs, lengths, widths))


def lane_points(name: str, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n points on lane centres, uniform in length: xy (n, 2), heading (n,) rad, lane width (n,)."""
    start, d, length, width = lanes(name)
    seg = rng.choice(len(length), size=n, p=length / length.sum())
    xy = start[seg] + d[seg] * (rng.random(n) * length[seg])[:, None]
    return xy, np.arctan2(d[seg, 1], d[seg, 0]), width[seg]


def random_camera(view: str, world: World, name: str, rng: np.random.Generator) -> PinholeCamera:
    """A camera of kind ``view`` (see the module docstring), 640 x 384 px."""
    h_px, w_px = INPUT_HW
    lens = LENSES[int(rng.integers(len(LENSES)))] if rng.random() < DISTORTED_SHARE else None
    dist = None if lens is None else list(lens[1:])
    fov = lambda lo, hi: lens[0] if lens is not None else rng.uniform(lo, hi)  # noqa: E731
    if view == "rsu":  # every pinned scenario has an RSU image camera
        base = rsu_camera(world.scenario.rsu)
        base_fov = np.rad2deg(2 * np.arctan(base.width / 2 / base.K[0, 0]))
        hfov = float(np.clip(fov(base_fov - 10, base_fov + 10), 50, 110))
        axis = base.R[2]
        yaw = np.arctan2(axis[1], axis[0]) + np.deg2rad(rng.uniform(-15, 15))
        pitch = -np.arcsin(axis[2]) + np.deg2rad(rng.uniform(-3, 3))
        pos = base.centre + [0.0, 0.0, rng.uniform(-2, 2)]
        pos[2] = max(pos[2], 3.0)
        return PinholeCamera.from_pose(pos, yaw, pitch, w_px, h_px, hfov, dist=dist)
    xy, heading, width = lane_points(name, rng, 1)
    if view == "pole":  # beside the lane, aimed at a point on it 15-70 m ahead or behind
        side = rng.choice([-1.0, 1.0])
        along = np.array([np.cos(heading[0]), np.sin(heading[0])])
        normal = np.array([-along[1], along[0]])
        pos = np.append(xy[0] + side * normal * rng.uniform(3.0, 12.0), rng.uniform(4.0, 12.0))
        aim = xy[0] + along * rng.choice([-1.0, 1.0]) * rng.uniform(15.0, 70.0)
        yaw = np.arctan2(*(aim - pos[:2])[::-1]) + np.deg2rad(rng.uniform(-15, 15))
        pitch = np.arctan2(pos[2], np.hypot(*(aim - pos[:2]))) + np.deg2rad(rng.uniform(-2, 2))
        return PinholeCamera.from_pose(pos, yaw, pitch, w_px, h_px, fov(50, 100), np.deg2rad(rng.normal(0, 1)),
                                       dist=dist)
    ego = Pose2D(float(xy[0, 0]), float(xy[0, 1]), float(heading[0] + np.deg2rad(rng.normal(0, 3))))
    return PinholeCamera.on_vehicle(ego, (1.0, 0.0, rng.uniform(1.2, 2.0)), 0.0, np.deg2rad(rng.uniform(-2, 6)),
                                    width=w_px, height=h_px, hfov_deg=fov(60, 100), dist=dist)


@lru_cache(maxsize=None)
def buildings(name: str, render_seed: int):
    """The union of a scenario's building footprints (shapely geometry, prepared)."""
    world, _ = scene(name, render_seed)
    polys = [shapely.Polygon(p) for p in world.building_polygons]
    for x, y, l, w, yaw in world.building_boxes:
        c, s = np.cos(yaw), np.sin(yaw)
        corners = np.array([[l, w], [-l, w], [-l, -w], [l, -w]]) / 2 @ np.array([[c, s], [-s, c]]) + [x, y]
        polys.append(shapely.Polygon(corners))
    union = shapely.union_all(polys) if polys else shapely.Polygon()
    shapely.prepare(union)
    return union


def candidate_bodies(name: str, rng: np.random.Generator, n: int) -> tuple:
    """n random bodies on the lanes: cls (n,), xy (n, 2), yaw (n,), lwh (n, 3)."""
    classes = list(BODY_PRIORS)
    cls = rng.choice(classes, size=n, p=[BODY_PRIORS[c][0] for c in classes])
    lwh = np.array([[rng.uniform(*r) for r in BODY_PRIORS[c][1:]] for c in cls])
    xy, heading, width = lane_points(name, rng, n)
    right = np.column_stack([np.sin(heading), -np.cos(heading)])  # right of the driving direction
    offset = rng.normal(0.0, 0.25, n)
    yaw = heading + rng.normal(0.0, 0.05, n)
    two_wheel = np.isin(cls, [C.CYCLIST, C.MOTORCYCLE])
    offset[two_wheel] = rng.uniform(0.0, 1.2, two_wheel.sum())
    ped = cls == C.PEDESTRIAN
    beside = ped & (rng.random(n) < 0.75)
    offset[beside] = rng.choice([-1.0, 1.0], beside.sum()) * (width[beside] / 2 + rng.uniform(0.3, 5.0, beside.sum()))
    crossing = ped & ~beside
    offset[crossing] = rng.uniform(-1.0, 1.0, crossing.sum()) * width[crossing]
    yaw[ped] = rng.uniform(-np.pi, np.pi, ped.sum())
    return cls.astype(np.int64), xy + right * offset[:, None], yaw, lwh


def place_bodies(name: str, render_seed: int, camera: PinholeCamera, rng: np.random.Generator, taken_xy: np.ndarray,
                 taken_r: np.ndarray, count: int) -> ObjectArray:
    """Up to ``count`` random bodies whose centres are in view (depth 3-150 m), none overlapping
    another (footprint discs of radius 0.45 hypot(l, w)) or ``taken`` discs, none in a building."""
    cls, xy, yaw, lwh = candidate_bodies(name, rng, 40 * count)
    uv, depth = camera.project(np.column_stack([xy, lwh[:, 2] / 2]))
    w, h = camera.width, camera.height
    ok = (depth > 3) & (depth < 150) & (uv[:, 0] > -0.05 * w) & (uv[:, 0] < 1.05 * w) & (uv[:, 1] > -0.05 * h) & (uv[:, 1] < 1.05 * h)
    ok &= ~shapely.contains_xy(buildings(name, render_seed), xy[:, 0], xy[:, 1])
    radius = 0.45 * np.hypot(lwh[:, 0], lwh[:, 1])
    keep, cx, cr = [], list(taken_xy), list(taken_r)
    for i in np.flatnonzero(ok):
        if len(keep) >= count:
            break
        if cx and np.any(np.hypot(*(np.asarray(cx) - xy[i]).T) < np.asarray(cr) + radius[i]):
            continue
        keep.append(i), cx.append(xy[i]), cr.append(radius[i])
    k = np.asarray(keep, dtype=np.int64)
    return ObjectArray(ids=EXTRA_ID0 + rng.permutation(100000)[: len(k)].astype(np.int64), cls=cls[k], xy=xy[k],
                       z=lwh[k, 2] / 2, lwh=lwh[k], yaw=yaw[k], vxy=np.zeros((len(k), 2)))


def world_bodies(world: World, t_s: float, camera: PinholeCamera) -> ObjectArray:
    """The world's actors at t_s and the ego (id 0), minus any body the camera sits in."""
    actors = world.actors_at(t_s)
    ego = world.ego_at(t_s)
    e = ObjectArray(ids=np.array([0]), cls=np.array([int(world.scenario.ego.cls)]), xy=np.array([[ego.x, ego.y]]),
                    z=world.ego_size[2:3] / 2, lwh=world.ego_size[None], yaw=np.array([ego.yaw]), vxy=np.zeros((1, 2)))
    bodies = ObjectArray.concat([actors, e])
    far = np.hypot(*(bodies.xy - camera.centre[:2]).T) > 0.5 * np.hypot(bodies.lwh[:, 0], bodies.lwh[:, 1]) + 1.0
    return bodies.take(far)


def render_frame(seed: int, k: int):
    """Frame k of a seed: (image (H, W, 3) uint8, BoxLabels, info: scenario, view, t_s, camera)."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(k,)))
    name = SCENARIOS[int(rng.integers(len(SCENARIOS)))]
    render_seed = int(rng.integers(RENDER_SEEDS))
    world, renderer = scene(name, render_seed)
    t_s = float(rng.uniform(0.0, world.duration_s))
    view = VIEWS[int(rng.choice(len(VIEWS), p=[p for _, p in VIEWS]))][0]
    camera = random_camera(view, world, name, rng)
    base = world_bodies(world, t_s, camera)
    taken_xy = np.vstack([base.xy, camera.centre[None, :2]])
    taken_r = np.append(0.45 * np.hypot(base.lwh[:, 0], base.lwh[:, 1]), 2.5)
    extra = place_bodies(name, render_seed, camera, rng, taken_xy, taken_r, int(rng.integers(3, 31)))
    frame = renderer.render_bodies(camera, ObjectArray.concat([base, extra]), rng if rng.random() < 0.8 else None)
    return frame.image, frame.labels, {"scenario": name, "view": view, "t_s": t_s, "camera": camera}


def _render_range(job: tuple) -> tuple[dict, list]:
    """Render frames [k0, k1) of ``seed`` into the memory-mapped ``images.npy``; their label rows."""
    path, seed, k0, k1 = job
    images = np.load(path, mmap_mode="r+")
    rows, infos = {k: [] for k in ("frame", "xyxy", "cls", "visible", "range_m", "ids")}, []
    for k in range(k0, k1):
        image, labels, info = render_frame(seed, k)
        images[k] = image
        for key, col in (("xyxy", labels.xyxy), ("cls", labels.cls), ("visible", labels.visible),
                         ("range_m", labels.range_m), ("ids", labels.ids)):
            rows[key].append(np.asarray(col))
        rows["frame"].append(np.full(len(labels), k, np.int64))
        infos.append({k: v for k, v in info.items() if k != "camera"})
    images.flush()
    return rows, infos


def render_dataset(out: Path, frames: int, seed: int, workers: int = 1) -> None:
    """Frames 0..frames-1 of ``seed`` into ``out`` (``detector_samples`` cache layout)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "images.npy"
    np.lib.format.open_memmap(path, mode="w+", dtype=np.uint8, shape=(frames, *INPUT_HW, 3)).flush()
    edges = np.linspace(0, frames, max(1, workers) * 4 + 1).astype(int)
    jobs = [(path, seed, int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    t0 = time.perf_counter()
    if workers > 1:
        with mp.get_context("fork").Pool(workers) as pool:
            parts = pool.map(_render_range, jobs)
    else:
        parts = [_render_range(job) for job in jobs]
    rows = {k: np.concatenate([np.concatenate(p[0][k]) if p[0][k] else np.zeros((0, 4) if k == "xyxy" else 0)
                               for p in parts]) for k in parts[0][0]}
    infos = [i for p in parts for i in p[1]]
    np.savez(out / "labels.npz", **rows)
    views = {v: sum(i["view"] == v for i in infos) for v, _ in VIEWS}
    meta = {"seed": seed, "frames": frames, "boxes": int(len(rows["cls"])), "views": views,
            "scenarios": list(SCENARIOS), "render_s": round(time.perf_counter() - t0, 1)}
    (out / "meta.json").write_text(json.dumps(meta, indent=1))
    print(json.dumps(meta), flush=True)
