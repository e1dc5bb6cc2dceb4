"""Survey the bundled scenarios' RSU cameras and calibrate them as an installer would (seeded).

For each bundled scenario, the landmarks a surveyor measures (RTK GNSS / total station,
~2 cm) and can find in the camera image:

- lane-marking ends: the ends of every dash of the dashed lines (the renderer's pattern,
  ``v2i.sim.ground_raster``: 3 m on / 6 m off in town, 6 m / 12 m on a highway, from each lane's
  start) and the ends of solid, centre, edge and kerb lines where the line stops or changes kind;
- stop-line ends (``v2i.sim.maps.road_network`` signals);
- building corners on the ground and 4 m and 8 m up the corner edge (the rendered buildings are
  12-25 m tall).

Kept: those in the image (3 px margin), in front, within min(range_m, 150 m) of the pole and not
hidden by a building (2-D line of sight from the pole, as ``v2i.sim.occlusion``); then spread out by
farthest-point sampling in the image (at most 24, at least 12 px apart). They are projected
through the TRUE camera (``v2i.sim.camera.rsu_camera``), clicked with Gaussian noise (0.7 px per
axis), surveyed with 2 cm noise (3 cm vertical on buildings; road marks are on the ground
plane z = 0), and one click is a gross mistake (20-40 px off) that RANSAC must reject. The
points go to ``src/v2i/perception/calibrations/<scenario>.points.csv``; then ``v2i camera calibrate`` (its
very ``run``) fits them with K from the lens's field of view and writes ``<scenario>.calib.json``,
and the map error on the visible lane centres at 20 / 50 / 80 m is printed. The RSU loads that
file, never the true pose.

    python tools/survey_points.py [--seed 0] [--out-dir src/v2i/perception/calibrations] [--scenario NAME ...]
"""

from __future__ import annotations

import argparse
import sys
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from v2i.perception.calibration import load_calibration
from v2i.sim.camera import PinholeCamera, rsu_camera
from v2i.sim.maps.road_network import CENTRE, DASHED, EDGE, KERB, SOLID, RoadNetwork, lane_bounds, road_network
from v2i.sim.occlusion import segments_hit_boxes, segments_hit_polygons
from v2i.sim.scenario import Scenario, bundled_scenarios, load_scenario
from v2i.sim.world import World
from v2i import camera_calibrate

URBAN_DASH_M, HIGHWAY_DASH_M = (3.0, 6.0), (6.0, 12.0)  # (on, off), as v2i.sim.ground_raster paints them
LINE_KINDS = (SOLID, CENTRE, EDGE, KERB)  # continuous lines: their ends are landmarks
BUILDING_HEIGHTS_M = (0.0, 4.0, 8.0)
CLICK_SIGMA_PX = 0.7
SURVEY_SIGMA_M = np.array([0.02, 0.02, 0.03])
OUTLIER_PX = (20.0, 40.0)
MAX_POINTS, MIN_SEPARATION_PX, MARGIN_PX = 24, 12.0, 3.0
MAX_RANGE_M = 150.0
PULL_BACK_M = 0.3  # line of sight ends this far short of a point, so its own building does not hide it


@dataclass(frozen=True)
class Landmark:
    xyz: np.ndarray  # (3,) m, map
    label: str


def _dash_ends(line: np.ndarray, on_m: float, off_m: float) -> np.ndarray:
    """Ends (K, 2) of the dashes painted along a polyline (K, 2) from its start."""
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(line, axis=0).T))])
    starts = np.arange(0.0, cum[-1], on_m + off_m)
    s = np.concatenate([starts, np.minimum(starts + on_m, cum[-1])])
    return np.column_stack([np.interp(s, cum, line[:, 0]), np.interp(s, cum, line[:, 1])])


def _line_ends(lines: list[tuple[str, np.ndarray]]) -> list[Landmark]:
    """Ends of continuous lines (kind, (K, 2)) that stop there: no line of the same kind
    leaves the same point in the opposite direction (that would be one line continuing)."""
    ends = []  # (kind, point, unit direction into the line)
    for kind, line in lines:
        for p, q in ((line[0], line[1]), (line[-1], line[-2])):
            ends.append((kind, p, (q - p) / np.linalg.norm(q - p)))
    out = []
    for kind, p, d in ends:
        continues = any(k == kind and np.linalg.norm(p2 - p) < 0.05 and d @ d2 < -0.95 for k, p2, d2 in ends)
        if not continues:
            out.append(Landmark(np.array([p[0], p[1], 0.0]), f"{kind} line end"))
    return out


def marking_landmarks(network: RoadNetwork) -> list[Landmark]:
    """Dash ends, line ends and stop-line ends of a road network, deduplicated (the signal heads
    of the map are not rendered, so nobody could click them)."""
    urban = any(lane.location == "urban" for lane in network.lanes)
    on, off = URBAN_DASH_M if urban else HIGHWAY_DASH_M
    marks, lines = [], []
    for lane in network.lanes:
        for side, kind in ((0, lane.left), (1, lane.right)):
            line = lane_bounds(lane)[side]
            if kind == DASHED:
                marks += [Landmark(np.array([x, y, 0.0]), "dash end") for x, y in _dash_ends(line, on, off)]
            elif kind in LINE_KINDS:
                lines.append((kind, line))
    marks += _line_ends(lines)
    for sig in network.signals:
        marks += [Landmark(np.array([x, y, 0.0]), f"stop line end, {sig.name}") for x, y in sig.stop_line]
    return _dedup(marks)


def building_landmarks(scenario: Scenario) -> list[Landmark]:
    """Footprint corners of every building on the ground and up its corner edge."""
    out = []
    for b in scenario.buildings:
        if b.box is not None:
            c, s = np.cos(np.deg2rad(b.box.yaw_deg)), np.sin(np.deg2rad(b.box.yaw_deg))
            local = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * [b.box.l / 2.0, b.box.w / 2.0]
            corners = np.array([b.box.x, b.box.y]) + local @ np.array([[c, s], [-s, c]])
        else:
            corners = np.asarray(b.polygon, dtype=float)
        for x, y in corners:
            out += [Landmark(np.array([x, y, z]), f"building corner {b.name}, {z:g} m up") for z in BUILDING_HEIGHTS_M]
    return out


def _dedup(marks: list[Landmark], tol_m: float = 0.05) -> list[Landmark]:
    out: list[Landmark] = []
    for m in marks:
        if all(np.linalg.norm(m.xyz - o.xyz) > tol_m for o in out):
            out.append(m)
    return out


def visible(camera: PinholeCamera, world: World, xyz: np.ndarray, max_range_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of points (N, 3) and whether each can be clicked: in the image, in front,
    in range and in line of sight from the pole (buildings only: the survey is done on an empty road)."""
    uv, depth = camera.project(xyz)
    pole = camera.centre[:2]
    rel = xyz[:, :2] - pole
    rng_m = np.hypot(rel[:, 0], rel[:, 1])
    inside = ((uv[:, 0] >= MARGIN_PX) & (uv[:, 0] <= camera.width - MARGIN_PX)
              & (uv[:, 1] >= MARGIN_PX) & (uv[:, 1] <= camera.height - MARGIN_PX))
    ok = (depth > 1.0) & inside & (rng_m <= max_range_m) & (rng_m > PULL_BACK_M)
    near = xyz[:, :2] - PULL_BACK_M * rel / np.maximum(rng_m, 1e-9)[:, None]
    origin = np.broadcast_to(pole, near.shape)
    blocked = segments_hit_boxes(origin, near, world.building_boxes).any(axis=1) if len(world.building_boxes) else 0
    if world.building_polygons:
        blocked = blocked | segments_hit_polygons(origin, near, world.building_polygons).any(axis=1)
    return uv, ok & ~np.asarray(blocked, dtype=bool)


def spread(uv: np.ndarray, most: int = MAX_POINTS, min_px: float = MIN_SEPARATION_PX) -> np.ndarray:
    """Indices of up to ``most`` pixels (N, 2) by farthest-point sampling, each >= ``min_px`` from
    those before; the first is the lowest in the image (the nearest ground)."""
    chosen = [int(np.argmax(uv[:, 1]))]
    dist = np.linalg.norm(uv - uv[chosen[0]], axis=1)
    while len(chosen) < most:
        k = int(np.argmax(dist))
        if dist[k] < min_px:
            break
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(uv - uv[k], axis=1))
    return np.array(chosen)


def survey(name: str, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, list[str], PinholeCamera]:
    """Clicked pixels (N, 2), surveyed map points (N, 3) and labels of a scenario's RSU camera."""
    scenario = load_scenario(name)
    camera, world = rsu_camera(scenario.rsu), World(scenario)
    marks = marking_landmarks(road_network(name)) + building_landmarks(scenario)
    xyz = np.array([m.xyz for m in marks])
    uv, ok = visible(camera, world, xyz, min(scenario.rsu.range_m, MAX_RANGE_M))
    idx = np.flatnonzero(ok)[spread(uv[ok])]
    clicks = uv[idx] + rng.normal(0.0, CLICK_SIGMA_PX, (len(idx), 2))
    # survey noise; marks on the road stay on the map's ground plane z = 0 (what a homography assumes)
    surveyed = xyz[idx] + rng.normal(0.0, 1.0, (len(idx), 3)) * SURVEY_SIGMA_M * [1.0, 1.0, 0.0]
    surveyed[:, 2] = np.where(xyz[idx, 2] > 0.0, xyz[idx, 2] + rng.normal(0.0, SURVEY_SIGMA_M[2], len(idx)), 0.0)
    labels = [marks[i].label for i in idx]
    bad = int(rng.integers(len(idx)))  # one gross mis-click (the wrong dash end, a slipped mouse)
    angle = rng.uniform(0.0, 2.0 * np.pi)
    clicks[bad] += rng.uniform(*OUTLIER_PX) * np.array([np.cos(angle), np.sin(angle)])
    clicks[bad] = np.clip(clicks[bad], 0.0, [camera.width - 1, camera.height - 1])
    labels[bad] += " (mis-clicked)"
    return clicks, surveyed, labels, camera


def write_points(path: Path, clicks: np.ndarray, xyz: np.ndarray, labels: list[str], header: str) -> None:
    rows = [f"{u:.2f},{v:.2f},{x:.3f},{y:.3f},{z:.3f}  # {label}" for (u, v), (x, y, z), label in zip(clicks, xyz, labels)]
    path.write_text(header + "u_px,v_px,x_m,y_m,z_m\n" + "\n".join(rows) + "\n", encoding="utf-8")


def lane_points(name: str, camera: PinholeCamera, step_m: float = 1.0) -> np.ndarray:
    """Ground points (N, 3) every ``step_m`` along every lane centre that the camera sees."""
    pts = []
    for lane in road_network(name).lanes:
        c = np.asarray(lane.centre, dtype=float)
        cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(c, axis=0).T))])
        s = np.arange(0.0, cum[-1], step_m)
        pts.append(np.column_stack([np.interp(s, cum, c[:, 0]), np.interp(s, cum, c[:, 1]), np.zeros(len(s))]))
    xyz = np.concatenate(pts)
    world = World(load_scenario(name))
    _, ok = visible(camera, world, xyz, np.inf)
    return xyz[ok]


def map_errors(calib_path: Path, name: str, camera: PinholeCamera, ranges_m=(20.0, 50.0, 80.0),
               half_bin_m: float = 2.5) -> dict[float, tuple[float, float]]:
    """Mean and largest ground error (m) of a calibration on the lane centres the camera sees,
    within +-``half_bin_m`` of each range from the pole: true pixel -> calibration -> map."""
    calib = load_calibration(calib_path)
    xyz = lane_points(name, camera)
    uv, _ = camera.project(xyz)
    err = np.linalg.norm(calib.px_to_map(uv)[0] - xyz[:, :2], axis=1)
    rng_m = np.hypot(*(xyz[:, :2] - camera.centre[:2]).T)
    out = {}
    for r in ranges_m:
        near = np.abs(rng_m - r) <= half_bin_m
        if near.any():
            out[r] = (float(err[near].mean()), float(err[near].max()))
    return out


def calibrate(name: str, seed: int, out_dir: Path) -> Path:
    """Survey, write the points, calibrate them with ``v2i camera calibrate``; the calib path."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(zlib.crc32(name.encode()),)))
    clicks, xyz, labels, camera = survey(name, rng)
    rsu = load_scenario(name).rsu
    hfov = rsu.image.fov_deg if rsu.image.fov_deg is not None else rsu.fov_deg
    points, calib = out_dir / f"{name}.points.csv", out_dir / f"{name}.calib.json"
    write_points(points, clicks, xyz, labels,
                 f"# {name}: RSU {rsu.id}, {camera.width}x{camera.height} px, {hfov:g} deg lens; surveyed landmarks\n"
                 f"# (RTK, 2 cm), clicked with {CLICK_SIGMA_PX} px noise, one mis-click; tools/survey_points.py --seed {seed}\n")
    parser = argparse.ArgumentParser(prog="v2i camera")
    camera_calibrate.add_parser(parser.add_subparsers(dest="camera_command"))
    camera_calibrate.run(parser.parse_args([
        "calibrate", "--points", str(points), "--out", str(calib), "--fov-deg", f"{hfov:g}",
        "--image-size", f"{camera.width}x{camera.height}", "--camera-id", rsu.id]))
    errors = map_errors(calib, name, camera)
    print("map error on the visible lane centres (mean / max) at "
          + ", ".join(f"{r:g} m: {m:.2f} / {x:.2f} m" for r, (m, x) in errors.items()))
    return calib


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seed", type=int, default=0, help="seed of the clicks and survey noise (default %(default)s)")
    shipped = Path(__file__).resolve().parents[1] / "src" / "v2i" / "perception" / "calibrations"
    p.add_argument("--out-dir", type=Path, default=shipped)
    p.add_argument("--scenario", action="append", help="only these bundled scenarios (default: all)")
    args = p.parse_args(argv)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    for name in args.scenario or bundled_scenarios():
        print(f"== {name}")
        calibrate(name, args.seed, args.out_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
