"""Where an OBU cycle's time goes with K RSUs x N objects: the OBU's own calls, in-process, no Zenoh.

    python benchmarks/scale_cycle.py --k 8 --n 100                # per-stage ms per cycle
    python benchmarks/scale_cycle.py --k 8 --n 100 --profile 25   # plus cProfile's top 25 by own time
    python benchmarks/scale_cycle.py --k 1,2,4,8 --n 50,100,200   # one summary line per configuration

The companion of ``benchmarks/scale.py`` (the live processes), free of process scheduling
and of the load others put on the machine: the same synthetic RSUs (``scale.Site``, the
same clocks, phases and latency) drive an ``ObuPipeline`` configured as ``v2i obu`` with the
K RSUs registered, through the calls the node makes, in simulated time: each RSU list is
encoded as the RSU sends it, then decoded and admitted as the OBU's inbox does (``obu_service.inbox``:
``open_body``, ``header_of``, ``admit_list``, ``from_body``, ``take_list``); each 10 Hz
cycle runs ``on_pose``, ``on_detections`` 50 ms after capture, ``fuse`` when ``ready``, the
output's ``encode``, then ``metrics`` and its ``encode``; time replies come back 1 ms after
each request. Each stage is timed with ``time.perf_counter`` (wall time of this process);
the table gives per cycle p50 / p99 / mean over the cycles after ``--warmup-s``.
"""

from __future__ import annotations

import argparse
import cProfile
import heapq
import pstats
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scale import CLOCK_OFFSET_STEP_NS, PERIOD_NS, Site, parse_list, site_rsus

from v2i.fusion.wire import states_from_objects
from obu_service.admission import AdmittedList
from obu_service.config import ObuConfig
from obu_service.pipeline import ObuPipeline
from rsu_service.pipeline import answer_time_request
from schemas.codec import encode, from_body, header_of, object_count, open_body
from schemas.messages import ObjectList, ObjectListHeader
from v2i.sim.obu_sources import SimulatedVehicle
from v2i.sim.scenario import load_scenario
from v2i.sim.scenario_site import scenario_site
from v2i.sim.world import World

START_NS = 1_700_000_000_000_000_000
FUSE_DELAY_NS = 50_000_000  # ObuConfig.fuse_delay_ms
LINK_NS = 500_000  # RSU publish -> OBU receive


class Driver:
    """The OBU's calls in simulated time; ``ms[stage]`` lists each call's CPU time (ms)."""

    def __init__(self, k: int, n: int, args):
        world = World(load_scenario(args.scenario))
        self.ids = list(site_rsus(args.scenario, k))
        budget = {"max_rsu_objects_per_cycle": args.max_rsu_objects} if args.max_rsu_objects else {}
        config = ObuConfig(scenario=args.scenario, known_rsus=site_rsus(args.scenario, k), start_at_ns=START_NS,
                           **budget)
        site = scenario_site(args.scenario)
        self.pipeline = ObuPipeline(config.pipeline_config(site), config.lanes(site))
        self.vehicle = SimulatedVehicle(world, args.seed, START_NS)
        seeds = np.random.SeedSequence(args.seed).spawn(2 * k)
        self.noise = [np.random.default_rng(s) for s in seeds[:k]]
        shared = Site(world, n, np.random.default_rng(seeds[k]))
        self.sites = [shared if args.objects == "shared" else Site(world, n, np.random.default_rng(s)) for s in seeds[k:]]
        self.rate_hz, self.latency_ns = args.rsu_rate_hz, round(args.rsu_latency_ms * 1e6)
        self.ms: dict[str, list[float]] = defaultdict(list)
        self.cycle_ms: list[dict[str, float]] = []
        self._events: list = []
        self._mark: dict[str, int] = {}  # calls per stage when the previous cycle went out

    def schedule(self, duration_s: float) -> None:
        end_ns = START_NS + round(duration_s * 1e9)
        period_ns = round(1e9 / self.rate_hz)
        for t in range(START_NS, end_ns, PERIOD_NS):
            heapq.heappush(self._events, (t, 1, "capture", None))
            heapq.heappush(self._events, (t + 10_000_000, 2, "sync", None))
        for i in range(len(self.ids)):
            for capture_ns in range(START_NS + i * period_ns // len(self.ids), end_ns, period_ns):
                heapq.heappush(self._events, (capture_ns + self.latency_ns + LINK_NS, 3, "list", (i, capture_ns)))

    def run(self) -> None:
        while self._events:
            t_ns, _, kind, arg = heapq.heappop(self._events)
            getattr(self, f"_{kind}")(t_ns, arg)

    def _timed(self, stage: str, fn, *args):
        t0 = time.process_time()
        out = fn(*args)
        self.ms[stage].append((time.process_time() - t0) * 1e3)
        return out

    def _capture(self, t_ns: int, _) -> None:
        frame = self.vehicle.capture(t_ns)
        self.pipeline.on_pose(frame.capture_ns, frame.pose)
        heapq.heappush(self._events, (t_ns + FUSE_DELAY_NS, 0, "fuse", frame))

    def _fuse(self, t_ns: int, frame) -> None:
        fuse_by_ns = self._timed("on_detections", self.pipeline.on_detections, frame.detections, frame.capture_ns)
        heapq.heappush(self._events, (fuse_by_ns, 0, "deadline", None))
        self._publish_if_ready(t_ns)

    def _deadline(self, t_ns: int, _) -> None:
        self._publish_if_ready(t_ns)

    def _publish_if_ready(self, t_ns: int) -> None:
        if not self.pipeline.ready(t_ns):
            return
        out = self._timed("fuse", self.pipeline.fuse, t_ns)
        self._timed("encode output", encode, out)
        self._timed("metrics + encode", lambda: encode(self.pipeline.metrics(t_ns)))
        # this cycle's work: everything since the previous cycle went out
        self.cycle_ms.append({stage: sum(v[self._mark.get(stage, 0):]) for stage, v in self.ms.items()})
        self._mark = {stage: len(v) for stage, v in self.ms.items()}

    def _sync(self, t_ns: int, _) -> None:
        request = self.pipeline.make_time_request(t_ns)
        for i, rsu_id in enumerate(self.ids):
            rsu_ns = t_ns + 500_000 + (i + 1) * CLOCK_OFFSET_STEP_NS
            reply = answer_time_request(request, rsu_id, rsu_ns, rsu_ns + 20_000)
            self.pipeline.on_time_reply(reply, t_ns + 1_020_000)

    def _list(self, t_ns: int, arg) -> None:
        i, capture_ns = arg
        offset_ns = (i + 1) * CLOCK_OFFSET_STEP_NS
        objs = self.sites[i].objects_at((capture_ns - START_NS) * 1e-9, self.noise[i])
        header = ObjectListHeader(rsu_id=self.ids[i], seq=(capture_ns - START_NS) // PERIOD_NS,
                                  capture_time_ns=capture_ns + offset_ns,
                                  publish_time_ns=t_ns - LINK_NS + offset_ns, sensor="synthetic")
        payload = encode(ObjectList(header=header, objects=states_from_objects(objs)))
        body = self._timed("decode header", open_body, payload, ObjectList)
        state = self._timed("admit_list", self.pipeline.admit_list, header_of(body), object_count(body), t_ns)
        if state is not None:
            msg = self._timed("decode objects", from_body, body, ObjectList)
            self._timed("take_list", self.pipeline.take_list, AdmittedList(msg, state, t_ns))


def stage_table(driver: Driver, warmup_cycles: int) -> str:
    """Per stage: calls per cycle and ms per cycle (p50, p99, mean) after warm-up."""
    cycles = driver.cycle_ms[warmup_cycles:]
    stages = sorted({s for c in cycles for s in c}, key=lambda s: -np.mean([c.get(s, 0.0) for c in cycles]))
    lines = [f"{'stage':>18} {'calls/cycle':>11} {'p50 ms':>8} {'p99 ms':>8} {'mean ms':>8}"]
    per_cycle_calls = {s: len(driver.ms[s]) / len(driver.cycle_ms) for s in stages}
    for stage in stages:
        v = np.array([c.get(stage, 0.0) for c in cycles])
        lines.append(f"{stage:>18} {per_cycle_calls[stage]:11.1f} {np.percentile(v, 50):8.2f} "
                     f"{np.percentile(v, 99):8.2f} {v.mean():8.2f}")
    cycle = np.array([c.get("fuse", 0) + c.get("encode output", 0) for c in cycles])
    total = np.array([sum(c.values()) for c in cycles])
    lines.append(f"{'fuse + encode':>18} {'':>11} {np.percentile(cycle, 50):8.2f} {np.percentile(cycle, 99):8.2f} "
                 f"{cycle.mean():8.2f}")
    lines.append(f"{'all OBU work':>18} {'':>11} {np.percentile(total, 50):8.2f} {np.percentile(total, 99):8.2f} "
                 f"{total.mean():8.2f}")
    return "\n".join(lines)


def run_config(k: int, n: int, args) -> Driver:
    """One configuration, run (under cProfile with ``--profile``); its stage table printed
    when it is the only one (or ``--stages``), else one summary line."""
    driver = Driver(k, n, args)
    driver.schedule(args.seconds)
    profiler = cProfile.Profile() if args.profile else None
    if profiler:
        profiler.enable()
    driver.run()
    if profiler:
        profiler.disable()
    refused = dict(driver.pipeline.rejected)
    if args.stages:
        print(f"K={k} N={n} ({args.objects}), {len(driver.cycle_ms)} cycles, modes "
              f"{ {m: c for m, c in driver.pipeline.modes.items() if c} }, refused {refused}"
              + (" (times under cProfile)" if profiler else ""))
        print(stage_table(driver, round(args.warmup_s * 10)))
    else:
        cycles = driver.cycle_ms[round(args.warmup_s * 10):]
        fuse = np.array([c.get("fuse", 0.0) + c.get("encode output", 0.0) for c in cycles])
        total = np.array([sum(c.values()) for c in cycles])
        print(f"{k:>3} {n:>4} {np.percentile(fuse, 50):10.2f} {np.percentile(fuse, 99):10.2f} "
              f"{np.percentile(total, 50):9.2f} {np.percentile(total, 99):9.2f} {total.mean() / 100 * 100:10.0f}  "
              f"{refused or ''}", flush=True)
    if profiler:
        pstats.Stats(profiler).sort_stats("tottime").print_stats(args.profile)
    return driver


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--k", type=parse_list, default=[8], help="RSU counts, e.g. 1,2,4,8 (default 8)")
    p.add_argument("--n", type=parse_list, default=[100], help="objects per RSU list, e.g. 50,100,200 (default 100)")
    p.add_argument("--seconds", type=float, default=20.0, help="simulated run (default 20)")
    p.add_argument("--warmup-s", type=float, default=5.0, help="cycles before this are not counted (default 5)")
    p.add_argument("--rsu-rate-hz", type=float, default=10.0)
    p.add_argument("--rsu-latency-ms", type=float, default=30.0)
    p.add_argument("--objects", choices=("shared", "distinct"), default="shared")
    p.add_argument("--scenario", default="red-light-runner")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-rsu-objects", type=int, help="the OBU's max_rsu_objects_per_cycle (default 1024)")
    p.add_argument("--stages", action="store_true", help="the per-stage table of each configuration "
                   "(the default for a single one)")
    p.add_argument("--profile", type=int, metavar="ROWS", help="also print cProfile's top ROWS functions by own time")
    args = p.parse_args(argv)
    args.stages = args.stages or len(args.k) * len(args.n) == 1
    if not args.stages:
        print("CPU ms per cycle (this process, in-process OBU calls); cpu% = all OBU work / 100 ms cycle")
        print(f"{'K':>3} {'N':>4} {'fuse+enc50':>10} {'fuse+enc99':>10} {'all p50':>9} {'all p99':>9} {'cpu% mean':>10}  refused")
    for k in args.k:
        for n in args.n:
            run_config(k, n, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
