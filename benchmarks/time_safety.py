"""Issue 31's acceptance runs: time safety over buffering links and clock steps (offline, fixed seeds).

Three tables, every number from ``v2i eval``'s report (the same pipeline objects, in process):

1. buffering: the red-light runner over ``rural-5g-buffered`` and over buffering profiles drawn here
   (each direction buffers in 15-50 s episodes, gaps ~ Exp(20 s), one of them from the start by seed:
   delays of tens of seconds delivered late and in order, written as scheduled ``hold`` windows),
   seeds x durations: ``clock_error_when_fused_max_ms`` against the tracking modes' bound,
   ``clock_steps_detected`` (must be 0: no step happened), output deadline misses, the V2I and the
   vehicle-only first detection;
2. steps: a 40 ms up / 10 ms down link, -85 ppm, an RSU clock step at 23.4 s: steps detected (1),
   ``clock_step_recovery_s`` (<= 3 s);
3. a -700 ms step at 8.0 s on lte-v2x: the target's track ids and id switches (0).

    python benchmarks/time_safety.py [--seeds 1-10] [--durations 30,90] [--workers 2] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from v2i.offline.runner import OfflineRun
from v2i.offline.spec import RunSpec

TRACKING_BOUND_MS = 50.0  # ObuPipelineConfig.max_clock_uncertainty_ms (the tracking modes' bound)
STEPS_MS = (-700.0, 700.0, -5000.0)
ASYMMETRIC = """name: asym-40-10
description: "40 ms up, 10 ms down, 0.5 ms jitter, no loss (biased: the clock error is 15 ms)"
uplink: {delay_ms: 40.0, jitter: {distribution: normal, std_ms: 0.5}}
downlink: {delay_ms: 10.0, jitter: {distribution: normal, std_ms: 0.5}}
"""
_BODY = ("{delay_ms: 20.0, jitter: {distribution: pareto, scale_ms: 20.0, shape: 4.0}, correlation: 0.4, "
         "loss_probability: 0.01, fifo: true, outage: {mode: hold, windows_s: %s}}")


def buffering_windows(rng: np.random.Generator, duration_s: float, from_start: bool) -> list[list[float]]:
    """One direction's buffering episodes [start, end] s: lengths ~ U(15, 50) s, gaps ~ Exp(20 s);
    ``from_start``: the first one begins at 0 (a run that starts buffered)."""
    windows, t = [], 0.0 if from_start else float(rng.exponential(20.0))
    while t < duration_s:
        end = t + float(rng.uniform(15.0, 50.0))
        windows.append([round(t, 3), round(end, 3)])
        t = end + float(rng.exponential(20.0))
    return windows


def buffering_profile(folder: Path, seed: int, duration_s: float) -> str:
    """A profile YAML (path) whose two directions buffer on their own draws; by seed, the uplink or the
    downlink (or neither) starts inside an episode."""
    rng = np.random.default_rng([31, seed, int(duration_s)])
    up, down = (buffering_windows(rng, duration_s, seed % 3 == k) for k in (0, 1))
    path = folder / f"buffered-{seed}-{int(duration_s)}.yaml"
    path.write_text(f"name: buffered-{seed}-{int(duration_s)}\ndescription: drawn by benchmarks/time_safety.py\n"
                    f"uplink: {_BODY % up}\ndownlink: {_BODY % down}\n")
    return str(path)


def run(spec: RunSpec) -> dict:
    """The report, with ``first_sync_s``: when the ego first had a clock estimate (None: never)."""
    runner = OfflineRun(spec)
    record = runner.execute()
    report = runner.report()
    samples = record.offset_samples()
    report["first_sync_s"] = float(samples[0, 0] - record.start_ns) * 1e-9 if len(samples) else None
    return report


def _row(label: str, report: dict) -> dict:
    return {
        "run": label, "fused_max_ms": report["clock_error_when_fused_max_ms"],
        "planning_max_ms": report["clock_error_when_planning_max_ms"],
        "steps": report["clock_steps_detected"], "recovery_s": report.get("clock_step_recovery_s"),
        "output_misses": report["output_deadline_miss_ratio"],
        "v2i_first_m": report["target"]["first_detection_distance_m"],
        "vehicle_only_first_m": report["vehicle_only"]["first_detection_distance_m"],
        "track_ids": report["target"]["track_ids"], "id_switches": report["target"]["id_switches"],
        "tracking_id_switches": report["tracking"]["id_switches"],
        "modes": report["mode_share"], "mode_reasons": report["mode_reasons"], "first_sync_s": report["first_sync_s"],
        # synced before the own sensors saw the target: V2I first detection should be the farther
        "synced_in_time": report["first_sync_s"] is not None and report["first_sync_s"] < (
            report["vehicle_only"]["first_detection_time_s"] or float("inf")),
    }


def _seeds(text: str) -> list[int]:
    first, _, last = text.partition("-")
    return list(range(int(first), int(last or first) + 1))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1-10", help="seeds of the buffering table, e.g. 1-10 (default %(default)s)")
    parser.add_argument("--durations", default="30,90", help="run lengths (s) of the buffering table (default %(default)s)")
    parser.add_argument("--workers", type=int, default=2, help="runs in parallel (default %(default)s)")
    parser.add_argument("--json", metavar="PATH", help="write every row as JSON")
    args = parser.parse_args(argv)
    durations = [float(d) for d in args.durations.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        asymmetric = folder / "asym-40-10.yaml"
        asymmetric.write_text(ASYMMETRIC)
        jobs = {}
        for d in durations:
            for seed in _seeds(args.seeds):
                jobs[f"buffering rural-5g-buffered {d:g} s seed {seed}"] = RunSpec(
                    profile="rural-5g-buffered", seed=seed, duration_s=d)
                jobs[f"buffering drawn {d:g} s seed {seed}"] = RunSpec(
                    profile=buffering_profile(folder, seed, d), seed=seed, duration_s=d)
        for step_ms in STEPS_MS:
            jobs[f"step {step_ms:+g} ms at 23.4 s, 40/10 ms link"] = RunSpec(
                profile=str(asymmetric), seed=1, rsu_clock_drift_ppm=-85.0, rsu_clock_step_ms=step_ms,
                rsu_clock_step_at_s=23.4)
        jobs["step -700 ms at 8.0 s, lte-v2x"] = RunSpec(seed=1, rsu_clock_step_ms=-700.0, rsu_clock_step_at_s=8.0)
        with ProcessPoolExecutor(args.workers) as pool:
            futures = {label: pool.submit(run, spec) for label, spec in jobs.items()}
            rows = []
            for k, (label, future) in enumerate(futures.items(), 1):
                rows.append(_row(label, future.result()))
                print(f"\r{k}/{len(futures)} runs", end="", file=sys.stderr, flush=True)
        print(file=sys.stderr)
    _print(rows)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


def _f(v, nd=1) -> str:
    return "-" if v is None else f"{v:.{nd}f}"


def _print(rows: list[dict]) -> None:
    buffering = [r for r in rows if r["run"].startswith("buffering")]
    print(f"{'run':44s} {'fused max ms':>12s} {'plan max ms':>11s} {'steps':>5s} {'out miss':>8s} "
          f"{'synced s':>8s} {'V2I m':>6s} {'VO m':>6s}")
    for r in buffering:
        print(f"{r['run']:44s} {_f(r['fused_max_ms'], 2):>12s} {_f(r['planning_max_ms'], 2):>11s} {r['steps']:>5d} "
              f"{r['output_misses']:>8.3f} {_f(r['first_sync_s']):>8s} {_f(r['v2i_first_m']):>6s} "
              f"{_f(r['vehicle_only_first_m']):>6s}")
    fused = [r["fused_max_ms"] for r in buffering if r["fused_max_ms"] is not None]
    in_time = [r for r in buffering if r["synced_in_time"]]
    print(f"buffering: {len(buffering)} runs, fused max {max(fused, default=0.0):.2f} ms (bound "
          f"{TRACKING_BOUND_MS:g} ms), steps detected {sum(r['steps'] for r in buffering)}, output misses "
          f"{sum(r['output_misses'] > 0 for r in buffering)} runs; synced before the own sensors saw the target "
          f"in {len(in_time)} runs, V2I first detection farther than vehicle-only in "
          f"{sum(1 for r in in_time if (r['v2i_first_m'] or 0) > (r['vehicle_only_first_m'] or 0))} of them")
    for r in in_time:
        if (r["v2i_first_m"] or 0) <= (r["vehicle_only_first_m"] or 0):
            print(f"  not farther: {r['run']}: outputs by mode_reason {r['mode_reasons']}")
    print()
    for r in rows[len(buffering):]:
        print(f"{r['run']:44s} steps {r['steps']}, recovery {_f(r['recovery_s'], 2)} s, target track ids "
              f"{r['track_ids']}, id switches {r['id_switches']} (tracking.id_switches {r['tracking_id_switches']}), "
              f"fused max {_f(r['fused_max_ms'], 1)} ms")


if __name__ == "__main__":
    sys.exit(main())
