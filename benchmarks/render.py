"""Renderer cost per frame (v2i.sim.render), the RSU camera path of ``v2i eval --rsu-source camera``.

    python benchmarks/render.py [--frames 50]

Prints, per scenario and view, the renderer's set-up time (ground raster, facades) and
ms per frame p50 / p95 / mean over ``--frames`` capture times spread over the scenario, clean
and with sensor noise. The first frame of a fixed camera also draws its static background
(sky, ground, buildings) and every actor's textures; it is reported apart ("first").
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from v2i.sim.camera import rsu_camera, vehicle_camera
from v2i.sim.render import SceneRenderer
from v2i.sim.scenario import VehicleCameraConfig, load_scenario
from v2i.sim.world import World


def bench(world: World, renderer: SceneRenderer, view: str, frames: int, noise: bool) -> tuple[float, np.ndarray, str]:
    """(first frame ms, steady frame ms (frames,), image size) for the RSU or ego camera."""
    cfg = world.scenario.ego_camera or VehicleCameraConfig()
    rng = np.random.default_rng(0) if noise else None
    times = np.linspace(0.0, world.duration_s, frames + 1)
    out = []
    for t in times:
        cam = rsu_camera(world.scenario.rsu) if view == "rsu" else vehicle_camera(cfg, world.ego_at(t))
        start = time.perf_counter()
        renderer.render(cam, t, rng, hide_ego=view == "ego")
        out.append((time.perf_counter() - start) * 1e3)
    return out[0], np.array(out[1:]), f"{cam.width}x{cam.height}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--scenarios", default="red-light-runner,dense-intersection")
    args = ap.parse_args()
    for name in args.scenarios.split(","):
        world = World(load_scenario(name))
        start = time.perf_counter()
        renderer = SceneRenderer(world, seed=0)
        setup_ms = (time.perf_counter() - start) * 1e3
        print(f"{name}: {len(world.ids)} actors, set-up {setup_ms:.0f} ms, ground texels {[round(g.res_m, 3) for g in renderer.ground]} m")
        for view in ("rsu", "ego"):
            for noise in (False, True):
                first, ms, size = bench(world, renderer, view, args.frames, noise)
                print(f"  {view:3s} {'noisy' if noise else 'clean'}: first {first:6.1f} ms, p50 {np.median(ms):5.1f} ms,"
                      f" p95 {np.percentile(ms, 95):5.1f} ms, mean {ms.mean():5.1f} ms per {size} frame"
                      f" ({len(ms)} frames)")


if __name__ == "__main__":
    main()
