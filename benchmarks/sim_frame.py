"""Simulation cost per frame: ground truth of all actors + one LiDAR frame with occlusion.

    python benchmarks/sim_frame.py [--actors 100] [--frames 50]

Prints ms per frame (p50 / p95) for the dense-intersection scenario (91 actors) and for
red-light-runner with ``--actors`` extra cars, so that growth with the actor count shows.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from v2i.sim.scenario import Scenario, load_scenario
from v2i.sim.sensors import Lidar
from v2i.sim.world import World


def with_extra_cars(name: str, extra: int) -> Scenario:
    data = load_scenario(name).model_dump(by_alias=True)
    for i in range(extra):
        lane_y = 1.75 + 3.5 * (i % 2)
        data["actors"].append({"name": f"extra{i}", "class": "car", "size": (4.0, 2.0, 1.6),
                               "trajectory": {"path": [(300.0 - 4 * i, lane_y), (-200.0, lane_y)],
                                              "speed": [(0.0, 5.0 + i % 7)]}})
    return Scenario.model_validate(data)


def frame_ms(scenario: Scenario, frames: int) -> np.ndarray:
    world = World(scenario)
    lidar = Lidar(scenario.lidar, np.random.default_rng(0))
    out = []
    for t in np.arange(frames) * 0.1:
        start = time.perf_counter()
        world.actors_at(t)
        lidar.detect(world, t)
        out.append((time.perf_counter() - start) * 1e3)
    return np.array(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--actors", type=int, default=100, help="extra cars added to red-light-runner")
    parser.add_argument("--frames", type=int, default=50)
    args = parser.parse_args()
    for label, scenario in (("dense-intersection", load_scenario("dense-intersection")),
                            (f"red-light-runner + {args.actors} cars", with_extra_cars("red-light-runner", args.actors))):
        ms = frame_ms(scenario, args.frames)
        print(f"{label:32s} {len(scenario.actors):4d} actors: {np.percentile(ms, 50):7.2f} ms p50, "
              f"{np.percentile(ms, 95):7.2f} ms p95 per frame")


if __name__ == "__main__":
    main()
