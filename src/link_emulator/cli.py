"""Command line of the link emulator (``v2i link ...``).

``v2i link --rsu-connect EP --vehicle-connect EP [--profile NAME]`` runs the relay;
``v2i link validate --profile NAME [--samples N] [--json -]`` checks a profile's channel
model against its declaration (see ``validate.py``).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import zenoh

from schemas.config import ConfigError, load_config
from sim.clock import SystemClock

from .config import LinkConfig
from .profile import DirectionProfile, TraceReplay, bundled_profiles, load_profile
from .relay import LinkRelay
from .validate import Settings, validate_direction


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the link emulator's options to ``parser``."""
    parser.add_argument(
        "--config", metavar="FILE", help="YAML file with LinkConfig fields; the options below override it"
    )
    parser.add_argument("--link-id", help="link name used in v2x/link/{link_id}/stats (default link1)")
    parser.add_argument(
        "--rsu-connect",
        metavar="EP",
        action="append",
        help="Zenoh endpoint of the RSU side, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    parser.add_argument(
        "--vehicle-connect",
        metavar="EP",
        action="append",
        help="Zenoh endpoint of the vehicle side, e.g. tcp/127.0.0.1:7448 (repeatable)",
    )
    parser.add_argument(
        "--profile",
        metavar="NAME|PATH",
        help="bundled link profile (see --list-profiles) or a profile YAML file (default lte-v2x)",
    )
    parser.add_argument("--seed", type=int, help="seed of the delay and loss draws (default 0)")
    parser.add_argument(
        "--duration",
        metavar="S",
        type=_positive_seconds,
        help="exit cleanly after S seconds (default: run until SIGINT or SIGTERM)",
    )
    parser.add_argument("--list-profiles", action="store_true", help="print the bundled profile names and exit")
    sub = parser.add_subparsers(dest="link_command", metavar="{validate}", required=False)
    text = "push N messages through a profile's channel model and compare with what it declares"
    configure_validate_parser(sub.add_parser("validate", help=text, description=text))


def configure_validate_parser(parser: argparse.ArgumentParser) -> None:
    """Options of ``v2i link validate``; its results go to ``run_validate``."""
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--profile", metavar="NAME|PATH", default="lte-v2x",
                        help="bundled profile or profile YAML file (default %(default)s)")
    source.add_argument("--trace", metavar="FILE", help="validate a replay of any CICV5G-format trace file instead")
    parser.add_argument("--direction", choices=["uplink", "downlink"], default="downlink",
                        help="direction to validate (default %(default)s)")
    parser.add_argument("--samples", type=_positive_int, default=1_000_000, help="messages sent (default %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the channel (default %(default)s)")
    parser.add_argument("--interval-ms", type=float, default=100.0, help="send period in ms (default %(default)s)")
    parser.add_argument("--size-bytes", type=int, default=1000, help="message size (default %(default)s)")
    parser.add_argument("--distance-m", type=float, help="sender-receiver distance (default: unknown, no PDR loss)")
    parser.add_argument("--json", metavar="PATH", help="write the report as JSON to PATH ('-' for stdout)")
    parser.add_argument("--check", action="store_true", help="exit 1 when an acceptance check fails")
    parser.set_defaults(func=run_validate)


def _positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value


def _positive_seconds(text: str) -> float:
    """argparse type: a duration in seconds > 0."""
    value = float(text)
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f"must be > 0 seconds, got {text}")
    return value


def run(args: argparse.Namespace) -> int:
    """Run the emulator until signalled (or ``--duration``).

    Returns 0 on a clean stop, 2 on a bad config or profile, 1 when Zenoh cannot start.
    """
    if args.list_profiles:
        print("\n".join(bundled_profiles()))
        return 0
    overrides = {
        "link_id": args.link_id,
        "rsu_connect": args.rsu_connect,
        "vehicle_connect": args.vehicle_connect,
        "profile": args.profile,
        "seed": args.seed,
    }
    try:
        config = load_config(LinkConfig, args.config, overrides)
        relay = LinkRelay(config, SystemClock())
    except ConfigError as exc:
        print(f"link emulator: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    with _stop_on_signals(stop), _stop_after(stop, args.duration):
        try:
            relay.open()
        except zenoh.ZError as exc:
            print(f"link emulator: cannot open Zenoh sessions: {exc}", file=sys.stderr)
            return 1
        _print_ready(config.link_id)
        relay.run(stop)
    return 0


def run_validate(args: argparse.Namespace) -> int:
    """``v2i link validate``: 0 when done (with ``--check``: 1 when a check fails), 2 on bad input."""
    try:
        name, direction = _validated_direction(args)
        if args.size_bytes < 0 or not args.interval_ms > 0.0:
            raise ValueError("--size-bytes must be >= 0 and --interval-ms > 0")
    except (ConfigError, ValueError) as exc:
        print(f"link validate: {exc}", file=sys.stderr)
        return 2
    settings = Settings(args.samples, args.seed, args.interval_ms, args.size_bytes, args.distance_m)
    report = validate_direction(name, args.direction, direction, settings)
    if args.json == "-":
        print(json.dumps(report, indent=2))
    else:
        print(format_report(report))
        if args.json:
            with open(args.json, "w", encoding="utf-8") as out:
                out.write(json.dumps(report, indent=2) + "\n")
    return 1 if args.check and not report["pass"] else 0


def _validated_direction(args: argparse.Namespace) -> tuple[str, DirectionProfile]:
    """(name, direction profile) to validate: a profile's direction or a trace replay."""
    if args.trace is not None:
        return args.trace, DirectionProfile(delay_ms=0.0, replay=TraceReplay(trace=args.trace))
    profile = load_profile(args.profile)
    return profile.name, getattr(profile, args.direction)


def format_report(report: dict) -> str:
    """A readable table of a validation report."""
    where = f", {report['distance_m']:g} m" if report["distance_m"] is not None else ""
    title = (f"profile {report['profile']} ({report['direction']}): {report['samples']} messages of "
             f"{report['size_bytes']} B every {report['interval_ms']:g} ms{where}, seed {report['seed']}")
    lines = [title, f"{'':16}{'declared':>12}{'achieved':>12}  declared by"]
    method = report["declared_method"]
    for key in ("mean_ms", "p50_ms", "p95_ms", "p99_ms", "loss_ratio", "mean_burst_len"):
        how = method["delay"] if key.endswith("_ms") else method[key]
        lines.append(f"{key:16}{_fmt(report['declared'][key]):>12}{_fmt(report['achieved'][key]):>12}  {how}")
    if "ks_statistic" in report:
        lines.append(f"KS statistic (achieved vs trace delays): {_fmt(report['ks_statistic'])}")
    checks = ", ".join(f"{name} {'ok' if ok else 'FAILED'}" for name, ok in report["checks"].items())
    lines.append(f"checks: {checks}")
    return "\n".join(lines)


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"


def _print_ready(link_id: str) -> None:
    """The one machine-readable line telling supervisors that the relay is up."""
    print(json.dumps({"event": "ready", "service": "link", "link_id": link_id}), flush=True)


@contextmanager
def _stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT and SIGTERM set ``stop`` (main thread only); previous handlers restored on exit."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@contextmanager
def _stop_after(stop: threading.Event, duration_s: float | None) -> Iterator[None]:
    """Set ``stop`` after ``duration_s`` seconds (None: never)."""
    if duration_s is None:
        yield
        return
    timer = threading.Timer(duration_s, stop.set)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
