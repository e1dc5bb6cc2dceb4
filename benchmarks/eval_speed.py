"""Offline evaluator speed per bundled scenario, as x real time (simulated s / wall s).

    python benchmarks/eval_speed.py [--scenarios a,b] [--seed 1] [--repeats 3] [--reference] [--stages] [--profile N]

Each scenario runs in this process exactly as ``v2i eval --scenario NAME --seed SEED`` runs it
(the same parser, spec and ``OfflineRun``; imports are paid once, before the first timing, and
reported apart as ``import_s``, with the loading of the tracker's compiled kernels). One line per scenario: simulated seconds, the median wall
seconds of ``--repeats`` runs (spec -> execute -> report) and their ratio. ``--reference``
also times each scenario with the numpy reference of the occlusion test
(``v2i.sim.occlusion.COMPILED = False``) in the same run, prints the speed-up and whether the two reports
(the JSON of ``v2i eval --json``) are equal. ``--profile N`` runs each
scenario once more under cProfile and prints its N costliest functions (cumulative).
``--stages`` runs each scenario once more with a timer around each function of ``STAGES``
and prints each one's exclusive wall seconds (time inside it, less time inside another timed
stage it calls) and share of the run; "other" is the event loop, links and glue.
"""

from __future__ import annotations

import argparse
import cProfile
import functools
import importlib
import json
import pstats
import statistics
import sys
import time

_T0 = time.perf_counter()
from v2i.offline.chaos import with_chaos
from v2i.offline.runner import OfflineRun
from v2i.sim import occlusion
from v2i.sim.scenario import bundled_scenarios
from v2i.runtime.process import freeze_heap
from v2i.cli import _spec, build_parser

from v2i.core.jit import load_kernels
from v2i.offline.kernels import RUN_KERNEL_MODULES

load_kernels(RUN_KERNEL_MODULES)  # the tracker's compiled loops: loaded once per process, like the imports
IMPORT_S = time.perf_counter() - _T0
freeze_heap()  # as v2i eval does before its run

# label -> "module:qualified name" of the functions timed by --stages
STAGES = {
    "scenario YAML": "v2i.sim.scenario:load_scenario",
    "LiDAR + localisation sim": "v2i.sim.obu_sources:SimulatedVehicle.capture",
    "RSU camera sim": "v2i.sim.rsu_sources:SimulatedCamera.capture",
    "occlusion": "v2i.sim.occlusion:visible_fraction",
    "RSU on_frame": "rsu_service.pipeline:RsuPipeline.on_frame",
    "RSU predictions": "rsu_service.pipeline:RsuPipeline.predictions",
    "codec encode": "schemas.codec:encode",
    "codec decode": "schemas.codec:decode",
    "OBU inbox": "obu_service.inbox:Inbox.take",
    "OBU take_list": "obu_service.pipeline:ObuPipeline.take_list",
    "OBU on_detections": "obu_service.pipeline:ObuPipeline.on_detections",
    "OBU fuse": "obu_service.pipeline:ObuPipeline.fuse",
    "OBU clock estimate": "v2i.clock.clock_sync:ClockSync.estimate_at",
    "scoring outputs": "v2i.offline.spec:RunRecord.add_output",
}


class StageTimer:
    """Exclusive wall seconds per stage: a stage's time less that of timed stages inside it."""

    def __init__(self):
        self.seconds: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        self._stack: list[list[float]] = []  # [start, seconds in timed children]

    def wrap(self, label: str, fn):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            self._stack.append([time.perf_counter(), 0.0])
            try:
                return fn(*args, **kwargs)
            finally:
                start, inner = self._stack.pop()
                spent = time.perf_counter() - start
                self.seconds[label] += spent - inner
                if self._stack:
                    self._stack[-1][1] += spent
        return timed

    def install(self) -> list:
        """Wrap every stage where it is looked up (its class, or each module holding the function)."""
        undo = []
        for label, where in STAGES.items():
            module, _, qualname = where.partition(":")
            owner = importlib.import_module(module)
            *path, name = qualname.split(".")
            for part in path:
                owner = getattr(owner, part)
            fn = getattr(owner, name)
            holders = [owner] if path else [m for m in list(sys.modules.values()) if getattr(m, name, None) is fn]
            for holder in holders:
                undo.append((holder, name, fn))
                setattr(holder, name, self.wrap(label, fn))
        return undo


def stages(name: str, seed: int) -> None:
    """Print each stage's exclusive seconds and share of one run."""
    timer = StageTimer()
    undo = timer.install()
    try:
        _, wall_s, _ = run_once(name, seed)
    finally:
        for holder, attr, fn in reversed(undo):
            setattr(holder, attr, fn)
    print(f"--- stages {name} (seed {seed}): {wall_s:.2f} s wall")
    for label, sec in sorted(timer.seconds.items(), key=lambda kv: -kv[1]):
        print(f"    {label:26s} {sec:6.2f} s {100 * sec / wall_s:5.1f} %")
    other = wall_s - sum(timer.seconds.values())
    print(f"    {'other':26s} {other:6.2f} s {100 * other / wall_s:5.1f} %")


def run_once(name: str, seed: int) -> tuple[float, float, dict]:
    """One ``v2i eval`` run in-process: (simulated s, wall s, its report)."""
    args = build_parser().parse_args(["eval", "--scenario", name, "--seed", str(seed)])
    start = time.perf_counter()
    run = OfflineRun(with_chaos(_spec(args), None), chaos=None)
    run.execute()
    report = run.report(driver="eval")
    wall_s = time.perf_counter() - start
    return run.duration_s, wall_s, report


def median_wall(name: str, seed: int, repeats: int, compiled: bool) -> tuple[float, float, str]:
    """(simulated s, median wall s of ``repeats`` runs, the report as JSON) with the compiled occlusion test
    or its numpy reference."""
    occlusion.COMPILED = compiled
    try:
        runs = [run_once(name, seed) for _ in range(repeats)]
    finally:
        occlusion.COMPILED = True
    return runs[0][0], statistics.median(w for _, w, _ in runs), json.dumps(runs[0][2], sort_keys=True)


def profile(name: str, seed: int, top: int) -> None:
    """Print the ``top`` functions by cumulative time of one run."""
    prof = cProfile.Profile()
    prof.runcall(run_once, name, seed)
    print(f"--- cProfile {name} (seed {seed}), top {top} by cumulative time")
    pstats.Stats(prof).sort_stats("cumulative").print_stats(top)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", help="comma-separated names (default: every bundled scenario)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per scenario; the median is printed")
    parser.add_argument("--reference", action="store_true",
                        help="also time the numpy reference of the occlusion test and compare the two runs' reports")
    parser.add_argument("--profile", type=int, metavar="N", help="print cProfile's N costliest functions per scenario")
    parser.add_argument("--stages", action="store_true", help="print exclusive wall seconds per stage (STAGES)")
    args = parser.parse_args()
    names = args.scenarios.split(",") if args.scenarios else bundled_scenarios()
    print(f"import_s {IMPORT_S:.2f} (imports and compiled kernels: paid once per v2i eval process, not in the times below)")
    head = f"{'scenario':24s} {'sim_s':>6s} {'wall_s':>7s} {'x_real':>7s}"
    print(head + (f" {'ref_wall_s':>10s} {'ref_x':>6s} {'speedup':>7s} same_report" if args.reference else ""))
    for name in names:
        sim_s, wall_s, report = median_wall(name, args.seed, args.repeats, compiled=True)
        line = f"{name:24s} {sim_s:6.1f} {wall_s:7.2f} {sim_s / wall_s:7.1f}"
        if args.reference:
            _, ref_s, ref_report = median_wall(name, args.seed, args.repeats, compiled=False)
            line += f" {ref_s:10.2f} {sim_s / ref_s:6.1f} {ref_s / wall_s:7.2f} {'yes' if ref_report == report else 'NO'}"
        print(line, flush=True)
    for name in names if args.stages else ():
        stages(name, args.seed)
    for name in names if args.profile else ():
        profile(name, args.seed, args.profile)


if __name__ == "__main__":
    main()
