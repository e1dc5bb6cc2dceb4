"""``v2i``: one command for the services, the live demo and the offline evaluator."""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path

SUBCOMMANDS = {
    "demo": "run RSU, link emulator and OBU as processes on loopback Zenoh and score the result",
    "eval": "run the same pipelines offline with a simulated clock and link (deterministic)",
    "chaos": "play a chaos timeline (link faults, service kills, an RSU clock step) during a live demo",
    "rsu": "run the roadside unit service",
    "obu": "run the on-board unit service",
    "link": "run the link emulator between RSU and vehicle",
}


def _run_options(p: argparse.ArgumentParser) -> None:
    from obu_service.pipeline import COMPENSATIONS, FUSION_METHODS, FUSION_MODES

    p.add_argument("--scenario", default="red-light-runner", help="bundled scenario name or YAML path (default %(default)s)")
    p.add_argument("--profile", default="lte-v2x", help="link profile: bundled name or YAML path (default %(default)s)")
    p.add_argument("--fusion", default="kf", choices=FUSION_METHODS, help="fusion method (default %(default)s)")
    p.add_argument("--fusion-mode", default="adaptive", choices=FUSION_MODES,
                   help="which RSU data a cycle fuses (seed 003): intra waits for the frame of the cycle's slot, "
                        "inter uses the newest buffered one, planning hands the RSU's 5 s paths to the planner; "
                        "adaptive picks the most accurate feasible one per cycle (default %(default)s)")
    p.add_argument("--compensation", default="predict", choices=COMPENSATIONS,
                   help="RSU delay compensation (default %(default)s); track-predict makes the RSU predict "
                        "and upsample, oosm (kf only) re-filters late RSU data at its own time")
    p.add_argument("--seed", type=int, default=0, help="seed of sensor noise and link model (default %(default)s)")
    p.add_argument("--duration", type=float, help="seconds of scenario to run (default: the scenario's duration)")
    p.add_argument("--rsu-clock-offset-ms", type=float, default=0.0, help="injected RSU clock offset, ms")
    p.add_argument("--rsu-clock-drift-ppm", type=float, default=0.0, help="injected RSU clock drift, ppm")
    p.add_argument("--rsu-clock-step-ms", type=float, default=0.0, help="injected RSU clock step, ms (see --rsu-clock-step-at-s)")
    p.add_argument("--rsu-clock-step-at-s", type=float, help="scenario time of the RSU clock step, s")
    p.add_argument("--deadline-ms", type=float, default=100.0, help="OBU end-to-end deadline per cycle (default %(default)s)")
    p.add_argument("--json", metavar="PATH", help="write the metrics JSON to PATH ('-' for stdout)")


def _spec(args: argparse.Namespace):
    from evaluation.spec import RunSpec

    return RunSpec(
        scenario=args.scenario, profile=args.profile, fusion=args.fusion, compensation=args.compensation,
        fusion_mode=args.fusion_mode, seed=args.seed, duration_s=args.duration,
        rsu_clock_offset_ms=args.rsu_clock_offset_ms, rsu_clock_drift_ppm=args.rsu_clock_drift_ppm,
        rsu_clock_step_ms=args.rsu_clock_step_ms, rsu_clock_step_at_s=args.rsu_clock_step_at_s,
        deadline_ms=args.deadline_ms,
    )


def _emit(report: dict, json_path: str | None) -> None:
    """Human summary (stderr when the JSON goes to stdout) and the JSON report."""
    from evaluation.spec import summary

    print(summary(report), file=sys.stderr if json_path == "-" else sys.stdout)
    if json_path == "-":
        print(json.dumps(report, indent=2))
    elif json_path:
        Path(json_path).write_text(json.dumps(report, indent=2) + "\n")


def _check_inputs(args: argparse.Namespace) -> None:
    """Fail early, with the reason, on a scenario or profile that cannot be loaded."""
    from link_emulator.profile import load_profile
    from sim.scenario import load_scenario

    load_scenario(args.scenario)
    load_profile(args.profile)
    if args.duration is not None and args.duration <= 0:
        raise ValueError("--duration must be positive")


def cmd_eval(args: argparse.Namespace) -> int:
    from evaluation.runner import OfflineRun
    from evaluation.spec import build_report

    _check_inputs(args)
    if args.table:
        return cmd_tables(args)
    chaos = None
    if args.chaos:
        from evaluation.chaos import load_chaos

        chaos = load_chaos(args.chaos)
    from evaluation.chaos import with_chaos

    run = OfflineRun(with_chaos(_spec(args), chaos), chaos=chaos)
    report = build_report(run.spec, run.world, run.execute(), driver="eval")
    if chaos:
        report["chaos"] = chaos.name
    _emit(report, args.json)
    return 0


def cmd_tables(args: argparse.Namespace) -> int:
    from evaluation.tables import run_tables, seed_tables, to_markdown, write_report

    seeds = list(range(args.seed, args.seed + args.seeds))
    tables = seed_tables(_spec(args))
    print(f"v2i eval: {sum(len(t.rows) for t in tables)} configurations x {len(seeds)} seeds", file=sys.stderr)
    results = run_tables(tables, seeds, workers=args.workers)
    if args.report:
        write_report(results, seeds, Path(args.report))
        print(f"v2i eval: wrote {args.report}/tables.md, tables.json and plots", file=sys.stderr)
    print(to_markdown(results, seeds))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from evaluation.demo import Demo, LinkOutage

    _check_inputs(args)
    outage = LinkOutage(args.kill_link_at, args.link_down_s) if args.kill_link_at is not None else None
    return _run_demo(Demo(_spec(args), startup_s=args.startup, outage=outage), args.json, "v2i demo")


def cmd_chaos_run(args: argparse.Namespace) -> int:
    from evaluation.chaos import load_chaos, with_chaos
    from evaluation.demo import Demo
    from link_emulator.profile import bundled_profiles

    _check_inputs(args)
    chaos = load_chaos(args.timeline)
    unknown = [e.profile for e in chaos.events if e.profile is not None and e.profile not in bundled_profiles()]
    if unknown:
        raise ValueError(f"chaos timeline {args.timeline}: profile {unknown[0]!r} is not bundled (the emulator "
                         f"switches to bundled profiles only): {', '.join(bundled_profiles())}")
    return _run_demo(Demo(with_chaos(_spec(args), chaos), startup_s=args.startup, chaos=chaos), args.json,
                     "v2i chaos run")


def _run_demo(demo, json_path: str | None, prog: str) -> int:
    """Run a live demo and emit its report; 1 when it failed, 130 when interrupted."""
    from evaluation.demo import DemoError, format_chaos

    _interrupt_on(signal.SIGINT, signal.SIGTERM)
    try:
        report = demo.run()
    except DemoError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; all services stopped", file=sys.stderr)
        return 130
    _emit(report, json_path)
    if chaos := format_chaos(report):
        print(chaos, file=sys.stderr if json_path == "-" else sys.stdout)
    return 0


def _interrupt_on(*signals: int) -> None:
    """Turn these signals into KeyboardInterrupt, even where a parent shell ignored them."""

    def _raise(signum, frame):
        raise KeyboardInterrupt

    for sig in signals:
        signal.signal(sig, _raise)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="v2i",
        description="Cooperative perception between a roadside unit and a vehicle over an emulated V2X link.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    parsers = {name: sub.add_parser(name, help=text, description=text) for name, text in SUBCOMMANDS.items()}
    for name in ("demo", "eval"):
        _run_options(parsers[name])
    ev = parsers["eval"]
    ev.add_argument("--table", choices=["seeds"], help="run the experiment tables (seed 000 Tables I-III, "
                    "seed 001 Table 1, OTVIC Table IV) instead of one run")
    ev.add_argument("--seeds", type=int, default=5, help="with --table: seeds --seed .. --seed+N-1 (default %(default)s)")
    ev.add_argument("--report", metavar="DIR", help="with --table: write tables.md, tables.json and PNG plots here")
    ev.add_argument("--workers", type=int, default=2, help="with --table: parallel runs (default %(default)s)")
    ev.add_argument("--chaos", metavar="FILE", help="chaos timeline YAML: timed link faults, service kills and "
                    "restarts, an RSU clock step (see evaluation/chaos.py)")
    ev.set_defaults(func=cmd_eval)
    demo = parsers["demo"]
    demo.add_argument("--startup", type=float, default=4.0, help="seconds given to the services to start (default %(default)s)")
    demo.add_argument("--kill-link-at", type=float, metavar="S", help="chaos: kill the link emulator S seconds into the run")
    demo.add_argument("--link-down-s", type=float, default=3.0, help="chaos: restart it this many seconds later (default %(default)s)")
    demo.set_defaults(func=cmd_demo)
    chaos_sub = parsers["chaos"].add_subparsers(dest="chaos_command", required=True, metavar="{run}")
    text = "play a chaos timeline YAML during a live demo and report each fault's effect"
    chaos_run = chaos_sub.add_parser("run", help=text, description=text + (
        ". Link events (profile, outage, delay_spike, loss_burst, bandwidth_cap) go to the link emulator "
        "as control messages at their scenario time; kill / restart act on the link or RSU process; the "
        "rsu_clock_step is set at the RSU's start. Timeline format: evaluation/chaos.py, examples/chaos/. "
        "The same timeline runs offline with v2i eval --chaos FILE."))
    chaos_run.add_argument("timeline", metavar="FILE", help="chaos timeline YAML, e.g. examples/chaos/outage-10s.yaml")
    _run_options(chaos_run)
    chaos_run.add_argument("--startup", type=float, default=4.0,
                           help="seconds given to the services to start (default %(default)s)")
    chaos_run.set_defaults(func=cmd_chaos_run)
    for name, module in (("rsu", "rsu_service.cli"), ("obu", "obu_service.cli"), ("link", "link_emulator.cli")):
        mod = __import__(module, fromlist=["configure_parser", "run"])
        mod.configure_parser(parsers[name])
        parsers[name].set_defaults(func=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as exc:
        print(f"v2i {args.command}: {exc}", file=sys.stderr)
        return 2
