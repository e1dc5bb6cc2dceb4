"""Write the Lanelet2 maps of the bundled scenarios into the package (src/v2i/sim/maps/<name>.osm).

    python tools/make_lanelet_maps.py [--out DIR] [--check]

Builds each road network of ``v2i.sim.maps.road_network``, writes it as Lanelet2 OSM (local-cartesian
projection about ``v2i.sim.maps.MAP_ORIGIN_*``), loads it back and checks that every lanelet's
centreline round-trips within 1 mm and that the routing graph has the expected successors.
``--check`` only compares freshly built maps with the shipped files (exit 1 if they differ).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import lanelet2
import numpy as np

from v2i.sim.maps.lanelet_build import load_map, write_map
from v2i.sim.maps.road_network import NETWORKS, road_network

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "src" / "v2i" / "sim" / "maps"


def roundtrip_error_m(network, loaded) -> float:
    """Largest distance (m) between a designed centreline vertex and the loaded one."""
    by_name = {ll.attributes["name"]: ll for ll in loaded.laneletLayer}
    worst = 0.0
    for lane in network.lanes:
        got = np.array([[p.x, p.y] for p in by_name[lane.name].centerline])
        worst = max(worst, float(np.max(np.hypot(*(got - lane.centre).T))))
    return worst


def summary(loaded) -> str:
    rules = lanelet2.traffic_rules.create(lanelet2.traffic_rules.Locations.Germany,
                                          lanelet2.traffic_rules.Participants.Vehicle)
    graph = lanelet2.routing.RoutingGraph(loaded, rules)
    lanelets = list(loaded.laneletLayer)
    n_succ = sum(len(graph.following(ll, False)) for ll in lanelets)
    n_lights = len(list(loaded.regulatoryElementLayer))
    return f"{len(lanelets)} lanelets, {n_succ} successor links, {n_lights} traffic lights"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--check", action="store_true", help="compare with the shipped files, write nothing")
    args = ap.parse_args(argv)
    status = 0
    for name in sorted(NETWORKS):
        network = road_network(name)
        target = args.out / f"{name}.osm"
        if args.check:
            with tempfile.TemporaryDirectory() as tmp:
                fresh = Path(tmp) / "map.osm"
                write_map(network, fresh)
                same = target.is_file() and fresh.read_bytes() == target.read_bytes()
            print(f"{name}: {'up to date' if same else 'DIFFERS from ' + str(target)}")
            status |= 0 if same else 1
            continue
        write_map(network, target)
        loaded = load_map(target)
        err = roundtrip_error_m(network, loaded)
        print(f"{target}: {summary(loaded)}; centreline round-trip error {err * 1e3:.3f} mm")
        status |= 0 if err < 1e-3 else 1
    return status


if __name__ == "__main__":
    sys.exit(main())
