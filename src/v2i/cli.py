"""``v2i``: one command for the services, the live demo and the offline evaluator."""

from __future__ import annotations

import argparse
import importlib
import math
import sys
from collections.abc import Iterable
from pathlib import Path

from v2i.console import check_folder, check_writable, emit, live, wrote

SUBCOMMANDS = {
    "demo": "run RSU, link emulator and OBU as processes on loopback Zenoh and score the result",
    "eval": "run the same pipelines offline with a simulated clock and link (deterministic)",
    "chaos": "play a chaos timeline (link faults, service kills, an RSU clock step) during a live demo",
    "rsu": "run the roadside unit service",
    "obu": "run the on-board unit service",
    "link": "run the link emulator between RSU and vehicle",
    "world": "run the simulated world in real time, publishing sensor inputs for services with --source zenoh",
    "router": "run a Zenoh router for sites with many RSUs and vehicles (the services attach as clients)",
    "camera": "camera tools: render a scenario's frames with ground-truth boxes, calibrate a camera from points",
    "fuzz": "send hostile messages to a live service and report what it refused, crashes, late outputs and memory",
    "monitor": "live dashboard of a running site (deadline misses, modes, delays, clock, link), or one JSON snapshot",
    "record": "record every v2x/** message heard at Zenoh endpoints into an MCAP file (Foxglove opens it)",
    "replay": "republish a recording on its keys in real or scaled time, or re-run a fresh OBU on it (--score)",
    "attack": "attack a running site near its RSU (ghosts, forgeries, replays, stolen and revoked keys, time, control) "
              "and report what was rejected and what got through (its keys: v2i pki attacker)",
    "pki": "the site's certificate authority: init, issue, revoke, list, a whole site, the attacker's keys, "
           "Zenoh TLS material",
    "warm": "compile the numba kernels of the services and the evaluator ahead of the first run (once per machine)",
    "wire": "wire tools: decode saved RSU object-list messages (CPM, SDSM, v2i) and print what they say",
}


def _run_options(p: argparse.ArgumentParser) -> None:
    from obu_service.pipeline import COMPENSATIONS, FUSION_METHODS, FUSION_MODES

    p.add_argument("--scenario", default="red-light-runner", help="bundled scenario name or YAML path (default %(default)s)")
    p.add_argument("--profile", default="lte-v2x", help="link profile: bundled name or YAML path (default %(default)s)")
    p.add_argument("--fusion", default="kf", choices=(*FUSION_METHODS, "roif"),
                   help="fusion method (default %(default)s); roif: image-level fusion of the ego's and the RSU's "
                        "camera boxes by ORB + RANSAC homography (Maqsud's thesis) on a scenario with an ego_camera, e.g. "
                        "--scenario roif-intersection: offline in v2i eval; live in v2i demo (RSU --source camera "
                        "--image-features at the ego camera's rate, the link, OBU --fusion roif)")
    p.add_argument("--fusion-mode", default="adaptive", choices=FUSION_MODES,
                   help="which RSU data a cycle fuses (IAAD, Liu et al.): intra waits for the frame of the cycle's slot, "
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
    p.add_argument("--rsu-source", default="sim", choices=("sim", "camera"),
                   help="RSU perception: sim, the camera noise model (fast), or camera: the scenario rendered by "
                        "the RSU's camera, through the ONNX detector and the shipped calibration (default %(default)s)")
    p.add_argument("--v2v", choices=("on", "off"), help="vehicles share their own perception with each other "
                   "(V2V, through a channel per vehicle pair; obu_service/peers.py): default as the scenario's v2v says")
    p.add_argument("--wire", default="v2i", choices=("v2i", "cpm", "sdsm"),
                   help="RSU object list encoding: v2i (compact msgpack columns), cpm (ETSI collective perception "
                        "message, UPER) or sdsm (SAE J3224's fields and resolution in UPER, but not J3224's bytes: "
                        "a J3224-2024 decoder reads none of v2i's SDSMs, and no other stack was tried; "
                        "docs/messages.md); the OBU fuses each at its resolution (default %(default)s)")
    p.add_argument("--cpm-rules", action="store_true",
                   help="with --wire cpm: the RSUs send by ETSI TS 103 324's generation rules (an object when new, "
                        "moved > 4 m, its speed changed > 0.5 m/s or its heading > 4 degrees since last sent, or 1 s "
                        "after; pedestrians and cyclists all together every 500 ms; a CPM over 1100 B in segments) "
                        "instead of every object in every list; the report adds rsu_lists (bytes, objects by rule)")
    p.add_argument("--security", choices=("strict", "permissive", "off", "none"),
                   help="signed V2X messages: the RSUs sign object lists, predictions and time replies "
                        "with a site PKI's certificates and the OBU verifies them: strict drops what fails (counted "
                        "as security_<reason>), permissive counts and fuses it, off unwraps unchecked; none: nothing "
                        "signed (default: strict for demo and chaos run, none for eval)")
    p.add_argument("--json", metavar="PATH", help="write the metrics JSON to PATH ('-' for stdout)")


def _spec(args: argparse.Namespace):
    from v2i.offline.spec import RunSpec

    return RunSpec(
        scenario=args.scenario, profile=args.profile, fusion=args.fusion, compensation=args.compensation,
        fusion_mode=args.fusion_mode, seed=args.seed, duration_s=args.duration,
        rsu_clock_offset_ms=args.rsu_clock_offset_ms, rsu_clock_drift_ppm=args.rsu_clock_drift_ppm,
        rsu_clock_step_ms=args.rsu_clock_step_ms, rsu_clock_step_at_s=args.rsu_clock_step_at_s,
        deadline_ms=args.deadline_ms, rsu_source=args.rsu_source,
        v2v=None if getattr(args, "v2v", None) is None else args.v2v == "on", wire=getattr(args, "wire", "v2i"),
        cpm_rules=bool(getattr(args, "cpm_rules", False)),
        security=_security(args),
    )


def _security(args: argparse.Namespace) -> str | None:
    """RunSpec.security of ``--security``: live runs sign by default (as deployed), eval does not."""
    policy = getattr(args, "security", None) or ("strict" if getattr(args, "command", None) in ("demo", "chaos")
                                                 else "none")
    return None if policy == "none" else policy


# RunSpec-backed config fields -> the flags that set them, so that errors name what the user typed
_FLAG_OF_FIELD = {
    "seed": "--seed", "deadline_ms": "--deadline-ms", "fusion": "--fusion", "compensation": "--compensation",
    "fusion_mode": "--fusion-mode", "scenario": "--scenario", "clock_offset_ms": "--rsu-clock-offset-ms",
    "clock_drift_ppm": "--rsu-clock-drift-ppm", "clock_step_ms": "--rsu-clock-step-ms",
    "clock_step_at_s": "--rsu-clock-step-at-s",
}
# flags (argparse dests) that must be finite and > 0, or finite and >= 0, when given
_POSITIVE_FLAGS = ("duration", "startup", "ready_timeout", "link_down_s", "seeds", "workers", "count", "rate")
_NON_NEGATIVE_FLAGS = ("kill_link_at",)


def _check_inputs(args: argparse.Namespace) -> None:
    """Fail early, with the reason, on a run that cannot be done: a scenario or profile that cannot
    be loaded, a bad flag value, RSU/OBU configs that do not validate, an output path that cannot be
    written (before a run of many seconds, not after it)."""
    from link_emulator.profile import load_profile
    from v2i.services import obu_scenario_site
    from v2i.sim.scenario import load_scenario

    load_scenario(args.scenario)
    load_profile(args.profile)
    _check_numbers(args)
    if args.fusion == "roif" and args.command != "demo":
        raise ValueError(f"--fusion roif runs in v2i eval and v2i demo, not v2i {args.command}")
    spec = _spec(args)
    spec.rsu_config()  # pydantic ValidationError: summarised by main with the flags' names
    obu_scenario_site(spec.obu_config())  # and the map the lane compensation needs
    if args.json not in (None, "-"):
        check_writable(Path(args.json), "--json")
    if getattr(args, "report", None):
        check_folder(Path(args.report), "--report")
    if getattr(args, "record", None):
        check_writable(Path(args.record), "--record")
    _save_wire(args)


SAVE_WIRE_HELP = ("save every object list each RSU sends, exactly as sent in the run's --wire (the bytes before any "
                  "signature), one file per list: DIR/<rsu-id>/NNNNNN.v2i.msgpack | NNNNNN.cpm.uper | "
                  "NNNNNN.sdsm.uper, NNNNNN counting that RSU's lists from 000000 in send order (continued after "
                  "files already there; 10^6 at most); the folder is created, an unwritable one refused at start "
                  "(docs/messages.md, 'Saved wire files')")


def _add_save_wire(p: argparse.ArgumentParser) -> None:
    p.add_argument("--save-wire", metavar="DIR", help=SAVE_WIRE_HELP)


def _save_wire(args: argparse.Namespace) -> str | None:
    """``--save-wire DIR``: the folder, absolute (the RSU processes run elsewhere), created and shown
    writable; None when not given. ValueError where the run sends no RSU object lists to save."""
    folder = getattr(args, "save_wire", None)
    if folder is None:
        return None
    if args.fusion == "roif" or getattr(args, "table", None):
        flag = "--fusion roif" if args.fusion == "roif" else "--table"
        raise ValueError(f"--save-wire saves one run's RSU object lists, not with {flag}")
    from v2i.runtime.wire_files import check_wire_folder

    return str(check_wire_folder(folder, "--save-wire").resolve())


def _check_numbers(args: argparse.Namespace) -> None:
    """ValueError naming the first flag of ``_POSITIVE_FLAGS`` / ``_NON_NEGATIVE_FLAGS`` out of range."""
    for dest in _POSITIVE_FLAGS + _NON_NEGATIVE_FLAGS:
        value = getattr(args, dest, None)
        if value is None:
            continue
        positive = dest in _POSITIVE_FLAGS
        if not math.isfinite(value) or value < 0 or (positive and value == 0):
            what = "a finite number > 0" if positive else "a finite number >= 0"
            raise ValueError(f"--{dest.replace('_', '-')} must be {what}, got {value:g}")


def cmd_eval(args: argparse.Namespace) -> int:
    from v2i.offline.runner import OfflineRun

    if args.fusion == "roif":
        return cmd_eval_roif(args)
    _check_inputs(args)
    if args.table:
        return cmd_tables(args)
    chaos = None
    if args.chaos:
        from v2i.offline.chaos import load_chaos

        chaos = load_chaos(args.chaos)
    from v2i.offline.chaos import with_chaos
    from v2i.runtime.process import freeze_heap

    freeze_heap()  # the start-up's objects: no full collection of them during the run
    run = OfflineRun(with_chaos(_spec(args), chaos), chaos=chaos, link_series=bool(args.report),
                     save_wire=_save_wire(args))
    run.execute()
    report = run.report(driver="eval")
    if chaos:
        report["chaos"] = chaos.name
    emit(report, args.json)
    for files in run.wire_files.values():
        print(f"v2i eval: {files.summary()}", file=sys.stderr)
    if args.report:
        from v2i.reports.run_report import write_offline_report

        wrote(write_offline_report(Path(args.report), report, run), "v2i eval")
    return 0


def cmd_eval_roif(args: argparse.Namespace) -> int:
    """Image-level fusion (Maqsud's ROIF thesis), offline: the ``image_fusion`` report."""
    from v2i.offline.image_fusion import run_image_fusion, summary
    from v2i.sim.scenario import load_scenario

    load_scenario(args.scenario)
    _check_numbers(args)
    if args.json not in (None, "-"):
        check_writable(Path(args.json), "--json")
    _no_run_report(args)
    _save_wire(args)
    report = run_image_fusion(args.scenario, seed=args.seed, duration_s=args.duration)
    emit(report, args.json, summary)
    return 0


def cmd_tables(args: argparse.Namespace) -> int:
    from v2i.offline.tables import run_tables, seed_tables, to_markdown, write_report

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
    from v2i.orchestration.demo import Demo, LinkOutage

    _check_inputs(args)
    if args.record and (args.fusion == "roif" or _is_site(args.scenario)):
        raise ValueError("--record records a single RSU and vehicle demo (not a site, not --fusion roif)")
    if args.metrics_ports is not None and (args.fusion == "roif" or _is_site(args.scenario)):
        raise ValueError("--metrics-ports serves a single RSU and vehicle demo (not a site, not --fusion roif)")
    if _is_site(args.scenario):
        return _run_site_demo(args)
    if args.fusion == "roif":
        return _run_roif_demo(args)
    outage = LinkOutage(args.kill_link_at, args.link_down_s) if args.kill_link_at is not None else None
    return _run_demo(Demo(_spec(args), outage=outage, record_to=args.record, progress=_progress(args),
                          metrics_ports=args.metrics_ports, pki_dir=args.pki, save_wire=_save_wire(args),
                          **_ready_timeout(args)),
                     args.json, "v2i demo", args.report)


def _ready_timeout(args: argparse.Namespace) -> dict:
    """The demo's ``ready_timeout_s`` from ``--ready-timeout`` (absent: its default); the old
    ``--startup`` (a guessed time zero) is accepted and ignored, with a note."""
    if getattr(args, "startup", None) is not None:
        print(f"v2i {args.command}: --startup is no longer used: the run starts when every service is ready "
              "(bound: --ready-timeout)", file=sys.stderr)
    return {} if args.ready_timeout is None else {"ready_timeout_s": args.ready_timeout}


def _progress(args: argparse.Namespace) -> str | None:
    """The live line's name (``v2i demo`` / ``v2i chaos run``), or None with ``--quiet``."""
    if getattr(args, "quiet", False):
        return None
    return "v2i chaos run" if args.command == "chaos" else "v2i demo"


def _is_site(scenario: str) -> bool:
    """More than one RSU or vehicle: ``v2i demo`` runs every node (``v2i.orchestration.site_demo``)."""
    from v2i.orchestration.site_demo import is_site
    from v2i.sim.scenario import load_scenario

    return is_site(load_scenario(scenario))


def _run_site_demo(args: argparse.Namespace) -> int:
    """``v2i demo`` of a scenario with several RSUs or vehicles: each node its own process."""
    from v2i.orchestration.site_demo import SiteDemo

    if args.kill_link_at is not None or args.fusion == "roif":
        flag = "--kill-link-at" if args.kill_link_at is not None else "--fusion roif"
        raise ValueError(f"{flag} runs a single RSU and vehicle; scenario {args.scenario!r} has several "
                         "(v2i demo runs every node of it, without chaos or image fusion)")
    return _run_demo(SiteDemo(_spec(args), progress=_progress(args), pki_dir=args.pki, save_wire=_save_wire(args),
                              **_ready_timeout(args)),
                     args.json, "v2i demo", args.report)


def _run_roif_demo(args: argparse.Namespace) -> int:
    """``v2i demo --fusion roif``: RSU camera + features, link, OBU image fusion; the ``image_fusion`` report."""
    from v2i.orchestration.image_fusion_demo import ImageFusionDemo, summary

    if args.kill_link_at is not None:
        raise ValueError("--kill-link-at is not supported with --fusion roif")
    _no_run_report(args)
    report = live(ImageFusionDemo(_spec(args), progress=_progress(args), pki_dir=args.pki,
                                  **_ready_timeout(args)).run, "v2i demo")
    if isinstance(report, int):
        return report
    emit(report, args.json, summary)
    return 0


def _no_run_report(args: argparse.Namespace) -> None:
    if getattr(args, "report", None) and not getattr(args, "table", None):
        raise ValueError("--report (the run's timeline and bird's-eye PNGs) is not supported with --fusion roif")


def cmd_chaos_run(args: argparse.Namespace) -> int:
    from v2i.offline.chaos import load_chaos, with_chaos
    from v2i.orchestration.demo import Demo
    from link_emulator.profile import bundled_profiles

    _check_inputs(args)
    if _is_site(args.scenario):
        raise ValueError(f"v2i chaos run plays a timeline on one RSU-vehicle link; scenario {args.scenario!r} "
                         "has several RSUs or vehicles")
    chaos = load_chaos(args.timeline)
    unknown = [e.profile for e in chaos.events if e.profile is not None and e.profile not in bundled_profiles()]
    if unknown:
        raise ValueError(f"chaos timeline {args.timeline}: profile {unknown[0]!r} is not bundled (the emulator "
                         f"switches to bundled profiles only): {', '.join(bundled_profiles())}")
    return _run_demo(Demo(with_chaos(_spec(args), chaos), chaos=chaos, record_to=args.record,
                          progress=_progress(args), pki_dir=args.pki, save_wire=_save_wire(args),
                          **_ready_timeout(args)),
                     args.json, "v2i chaos run", args.report)


def cmd_fuzz(args: argparse.Namespace) -> int:
    from v2i.adversary.fuzz import summary
    from v2i.adversary.fuzz_targets import TARGETS

    _check_numbers(args)
    if args.json not in (None, "-"):
        check_writable(Path(args.json), "--json")
    kinds = args.kinds.split(",") if args.kinds else None
    if args.target == "frames":
        from v2i.adversary.fuzz_frames import FramesFuzz as target
    elif args.target == "obu-v2v":
        from v2i.adversary.fuzz_v2v import ObuV2vFuzz as target
    elif args.target == "obu-signed":
        from v2i.adversary.fuzz_signed import ObuSignedFuzz as target
    elif args.fusion == "roif":
        if args.target != "obu":
            raise ValueError("--fusion roif fuzzes the OBU only: v2i fuzz --target obu --fusion roif")
        from v2i.adversary.fuzz_roif import ObuRoifFuzz as target
    else:
        target = TARGETS[args.target]
    run = target(args.count, seed=args.seed, rate_hz=args.rate, kinds=kinds, **_ready_timeout(args))
    report = live(run.run, "v2i fuzz")
    if isinstance(report, int):
        return report
    emit(report, args.json, summary)
    return 1 if report["crashes"] or report["outputs"]["late"] or report["outputs"]["missing"] else 0


def _run_demo(demo, json_path: str | None, prog: str, report_dir: str | None = None) -> int:
    """Run a live demo and emit its report (and its PNGs into ``report_dir``); 1 when it failed,
    130 when interrupted."""
    from v2i.reports.chaos_summary import format_chaos

    report = live(demo.run, prog)
    if isinstance(report, int):
        return report
    emit(report, json_path)
    if chaos := format_chaos(report):
        print(chaos, file=sys.stderr if json_path == "-" else sys.stdout)
    if report_dir:
        from v2i.reports.run_report import write_demo_report

        wrote(write_demo_report(Path(report_dir), report, demo), prog)
    return 0


def build_parser(commands: Iterable[str] | None = None) -> argparse.ArgumentParser:
    """The ``v2i`` parser; only ``commands`` (default: all) get their options, so that a command
    imports no other command's modules (``v2i --help`` imports none: ``benchmarks/cli_start.py``)."""
    parser = _OneLineParser(
        prog="v2i",
        description="Cooperative perception between a roadside unit and a vehicle over an emulated V2X link.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    parsers = {name: sub.add_parser(name, help=text, description=text) for name, text in SUBCOMMANDS.items()}
    for name in SUBCOMMANDS if commands is None else commands:
        _OPTIONS[name](parsers[name])
    return parser


def _eval_options(ev: argparse.ArgumentParser) -> None:
    _run_options(ev)
    ev.add_argument("--table", choices=["seeds"], help="run the experiment tables (Saravanan et al. Tables I-III, "
                    "Bidare's poster Table 1, OTVIC Table IV) instead of one run")
    ev.add_argument("--seeds", type=int, default=5, help="with --table: seeds --seed .. --seed+N-1 (default %(default)s)")
    ev.add_argument("--report", metavar="DIR", help="write pictures of the run here: timeline.png (modes, latency and "
                    "misses, RSU delay and data age, clock error, target error; chaos shaded), bev.png (truth vs "
                    "fused target) and report.json; with --table: tables.md, tables.json and PNG plots instead")
    ev.add_argument("--workers", type=int, default=2, help="with --table: parallel runs (default %(default)s)")
    ev.add_argument("--chaos", metavar="FILE", help="chaos timeline YAML: timed link faults, service kills and "
                    "restarts, an RSU clock step (see evaluation/chaos.py)")
    _add_save_wire(ev)
    ev.set_defaults(func=cmd_eval)


_REPORT_HELP = ("after the run, write pictures of it here: timeline.png (timeline-<vehicle>.png per vehicle of a "
                "site: modes, latency and misses, RSU delay and data age, clock error, target error; chaos "
                "faults shaded), bev.png (truth vs the fused target) and report.json")


_RECORD_HELP = ("record both sides of the link (RSU, vehicle after the link, link stats) with the run's spec into "
                "this MCAP file while the run goes; v2i replay FILE --score re-runs a fresh OBU on it")


_PKI_HELP = ("the site PKI (v2i pki) the services sign and verify with: created if absent, completed with a "
             "certificate for every RSU, vehicle and the operator that lacks one (default: a fresh one in the run's "
             "temporary directory); prepare extra subjects or revocations here before the run")


READY_TIMEOUT_HELP = ("seconds every service may take to say it is ready (default 120); the run's scenario clock "
                      "starts when all are, so a busy machine only starts later. A progress line shows who is "
                      "awaited; a service that dies or is not ready in time is named with its last log lines")


def _add_ready_timeout(p: argparse.ArgumentParser) -> None:
    """``--ready-timeout S``, and the old ``--startup`` (a guessed time zero), hidden: ignored with a note."""
    p.add_argument("--ready-timeout", type=float, metavar="S", help=READY_TIMEOUT_HELP)
    p.add_argument("--startup", type=float, help=argparse.SUPPRESS)
QUIET_HELP = ("no live line on stderr while the run goes (elapsed s, output and RSU deadline misses, mode, RSU "
              "lists, chaos events: rewritten in place on a terminal, a plain line every 5 s otherwise)")


def _demo_options(demo: argparse.ArgumentParser) -> None:
    _run_options(demo)
    demo.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    _add_ready_timeout(demo)
    demo.add_argument("--kill-link-at", type=float, metavar="S", help="chaos: kill the link emulator S seconds into the run")
    demo.add_argument("--link-down-s", type=float, default=3.0, help="chaos: restart it this many seconds later (default %(default)s)")
    demo.add_argument("--record", metavar="FILE", help=_RECORD_HELP)
    demo.add_argument("--report", metavar="DIR", help=_REPORT_HELP)
    demo.add_argument("--pki", metavar="DIR", help=_PKI_HELP)
    demo.add_argument("--metrics-ports", type=_metrics_base, metavar="BASE",
                      help="serve each service's Prometheus /metrics on 127.0.0.1: rsu BASE, link BASE+1, obu BASE+2 "
                           "(e.g. 9101: the ports of deploy/prometheus/prometheus.yml); default: none")
    _add_save_wire(demo)
    demo.set_defaults(func=cmd_demo)


def _metrics_base(text: str) -> int:
    """argparse type of ``--metrics-ports``: a port that leaves room for the two after it."""
    value = int(text)
    if not 1 <= value <= 65533:
        raise argparse.ArgumentTypeError(f"must be a TCP port 1..65533 (three ports from it), got {text}")
    return value


def _chaos_options(chaos: argparse.ArgumentParser) -> None:
    chaos_sub = chaos.add_subparsers(dest="chaos_command", required=True, metavar="{run}")
    text = "play a chaos timeline YAML during a live demo and report each fault's effect"
    chaos_run = chaos_sub.add_parser("run", help=text, description=text + (
        ". Link events (profile, outage, delay_spike, loss_burst, bandwidth_cap) go to the link emulator "
        "as control messages at their scenario time; kill / restart act on the link or RSU process; the "
        "rsu_clock_step is set at the RSU's start. Timeline format: evaluation/chaos.py, examples/chaos/. "
        "The same timeline runs offline with v2i eval --chaos FILE."))
    chaos_run.add_argument("timeline", metavar="FILE", help="chaos timeline YAML, e.g. examples/chaos/outage-10s.yaml")
    _run_options(chaos_run)
    chaos_run.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    _add_ready_timeout(chaos_run)
    chaos_run.add_argument("--report", metavar="DIR", help=_REPORT_HELP)
    chaos_run.add_argument("--record", metavar="FILE", help=_RECORD_HELP)
    chaos_run.add_argument("--pki", metavar="DIR", help=_PKI_HELP)
    _add_save_wire(chaos_run)
    chaos_run.set_defaults(func=cmd_chaos_run)


def _fuzz_options(fuzz: argparse.ArgumentParser) -> None:
    fuzz.description += (". obu: an RSU and the OBU, the attacker publishing on the RSU keys (spoofed and fake "
                         "ids, floods, replays) and forging time replies; rsu: hostile time queries; link: hostile "
                         "lists, poses, controls and queries on both sides of the emulator. Exit code 1 when the "
                         "target crashed or an output was late or missing.")
    fuzz.add_argument("--target", required=True, choices=("obu", "rsu", "link", "frames", "obu-inputs", "rsu-inputs", "obu-v2v",
                                                    "obu-signed"),
                      help="the service to attack; frames: hostile image files in the RSU's recording "
                           "(--source video), read at min(--rate, 20) frames/s; obu-inputs / rsu-inputs: the "
                           "service with --source zenoh fed by v2i world, hostile SensorObjects / "
                           "LocalizationPose on its sensor keys; obu-v2v: the OBU with --v2v, hostile peer "
                           "shared lists, time requests and replies on the V2V keys (v2i.adversary.fuzz_v2v); obu-signed: RSU and "
                           "OBU with a site PKI and --security strict, hostile signed envelopes (kinds garbage_prefix, "
                           "truncated, huge_fields, bit_flips, signed_hostile: hostile payloads validly signed, "
                           "special: replays; v2i.adversary.fuzz_signed)")
    fuzz.add_argument("--fusion", choices=("roif",), help="with --target obu: an OBU fusing images (--fusion roif) "
                      "under hostile RsuImageFeatures (kinds: malformed, wrong_type, unknown_keys, non_finite, "
                      "out_of_image, oversized_counts, wrong_descriptor_length, bad_index, absurd_times, edge_valid, "
                      "special: flood, fake_id, replay); RSU and OBU on roif-intersection")
    fuzz.add_argument("--count", type=int, default=10_000, help="hostile messages to send (default %(default)s)")
    fuzz.add_argument("--rate", type=float, default=2000.0, help="messages per second (default %(default)s)")
    fuzz.add_argument("--seed", type=int, default=0, help="seed of the hostile messages (default %(default)s)")
    fuzz.add_argument("--kinds", metavar="K1,K2", help="only these kinds of hostile message (default: all): "
                      "random_bytes, truncated, bit_flips, wrong_envelope, header_version, unknown_keys, "
                      "wrong_shapes, non_finite, extreme_values, absurd_times, oversized, large_malformed, and "
                      "special (the target's floods, fake ids, replays); for frames: random_bytes, truncated, "
                      "empty, pixel_bomb, wrong_size, deep, huge_file; trickle (alone; obu, rsu, link): no message "
                      "but 300 raw TCP sockets at the target's listen endpoint, each a byte every 300 / --rate s, "
                      "for --count / --rate s (--count 3000 --rate 150: a byte every 2 s for 20 s)")
    _add_ready_timeout(fuzz)
    fuzz.add_argument("--json", metavar="PATH", help="write the report JSON to PATH ('-' for stdout)")
    fuzz.set_defaults(func=cmd_fuzz)


def _camera_options(camera: argparse.ArgumentParser) -> None:
    camera_sub = camera.add_subparsers(dest="camera_command", required=True, metavar="{render,calibrate}")
    for module in ("v2i.camera_render", "v2i.camera_calibrate"):
        importlib.import_module(module).add_parser(camera_sub)


def _service_options(module: str, run: str | None = None):
    """Options of a service command from its module's ``configure_parser`` and ``--zenoh-config``;
    runs its ``run``, or ``v2i.services``' function named ``run`` (the RSU and OBU: the composition
    root hands them their site, sources and clocks)."""

    def options(p: argparse.ArgumentParser) -> None:
        mod = importlib.import_module(module)
        mod.configure_parser(p)
        p.add_argument("--zenoh-config", dest="site_zenoh_config", metavar="FILE",
                       help="Zenoh JSON5 file merged into every session of this command (TLS, mutual TLS, "
                            "access control: deploy/zenoh/); the same as $V2I_ZENOH_CONFIG")
        p.set_defaults(func=mod.run if run is None else getattr(importlib.import_module("v2i.services"), run))

    return options


def _warm_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--check", action="store_true", help="exit 1 when a kernel had to be compiled (the cache was "
                   "empty or stale), e.g. to show that an image or a CI cache holds them")
    p.set_defaults(func=cmd_warm)


def cmd_warm(args: argparse.Namespace) -> int:
    """``v2i warm``: every compiled kernel loaded or compiled (progress on stderr), one closing line."""
    from v2i.core.jit import warm
    from v2i.offline.kernels import ALL_KERNEL_MODULES

    line, compiled = warm(ALL_KERNEL_MODULES)
    print(line)
    return 1 if args.check and compiled else 0


def _wire_options(p: argparse.ArgumentParser) -> None:
    """``v2i wire``: files only, so no --zenoh-config (its configure_parser sets its ``run``)."""
    importlib.import_module("v2i.wire_cli").configure_parser(p)


def _pki_options(p: argparse.ArgumentParser) -> None:
    """``v2i pki``: files only, so no --zenoh-config (its configure_parser sets its ``run``)."""
    importlib.import_module("v2i.security.pki_cli").configure_parser(p)


# command -> the function adding its options (and importing its modules: only when it is parsed)
_OPTIONS = {
    "demo": _demo_options, "eval": _eval_options, "chaos": _chaos_options,
    "rsu": _service_options("rsu_service.cli", "run_rsu"), "obu": _service_options("obu_service.cli", "run_obu"),
    "link": _service_options("link_emulator.cli"),
    "world": _service_options("v2i.world_node"), "router": _service_options("v2i.router"),
    "camera": _camera_options, "fuzz": _fuzz_options, "monitor": _service_options("v2i.monitor"),
    "record": _service_options("v2i.record"), "replay": _service_options("v2i.replay"),
    "attack": _service_options("v2i.adversary.attack"),
    "pki": _pki_options,
    "warm": _warm_options, "wire": _wire_options,
}


def _named_command(argv: list[str]) -> list[str]:
    """The command that ``argv`` runs (the first word; ``v2i`` has no option but --help), or none."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return [word] if word in SUBCOMMANDS else []


class _OneLineParser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors are one line on stderr (exit 2), not usage + message."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def main(argv: list[str] | None = None) -> int:
    """Run a ``v2i`` command; bad input of any kind is one line on stderr and exit code 2."""
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser(_named_command(argv)).parse_args(argv)
    sub_command = getattr(args, f"{args.command}_command", None)  # chaos run, camera render, ...
    prog = f"v2i {args.command}" + (f" {sub_command}" if sub_command else "")
    try:
        if getattr(args, "site_zenoh_config", None):  # --zenoh-config: checked, then the process's site config
            from v2i.runtime.transport import use_config_file

            use_config_file(args.site_zenoh_config)
        return args.func(args)
    except (ValueError, OSError) as exc:  # pydantic's ValidationError is a ValueError
        from v2i.runtime.config import one_line_error

        print(f"{prog}: {one_line_error(exc, _FLAG_OF_FIELD)}", file=sys.stderr)
    return 2
