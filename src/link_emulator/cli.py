"""Command line of the link emulator (``v2i link ...``).

``v2i link --rsu-connect EP --vehicle-connect EP [--profile NAME]`` runs the relay for one
vehicle; ``v2i link --rsu-connect EP --vehicle ID=EP[,EP] --vehicle ID=EP ...`` for several, one
channel per RSU-vehicle pair (one emulator per RSU, see ``relay.py``);
``v2i link --v2v --vehicle ID=EP --vehicle ID=EP ...`` relays the vehicles' V2V messages to each
other, one channel per ordered vehicle pair (one V2V emulator per site, see ``v2v_relay.py``);
``v2i link validate --profile NAME [--samples N] [--json -]`` checks a profile's channel
model against its declaration (see ``validate.py``);
``v2i link set --connect EP (--profile NAME | --clear | --outage S | ...)`` changes a running
emulator's link through its control endpoint (``--control-listen``).
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import zenoh

from v2i.runtime.config import ConfigError, load_config, one_line_error
from v2i.runtime.site import load_site
from v2i.runtime.process import freeze_heap, limit_malloc_arenas, log
from v2i.security.pki import PkiError
from v2i.core.clock import SystemClock
from v2i.telemetry.metrics_cli import MetricsPortError, add_metrics_options, metrics_server

from link_emulator.config import MAX_VEHICLES, LinkConfig
from link_emulator.control_client import SET_DESCRIPTION, configure_set_parser, positive_seconds
from link_emulator.profile import DirectionProfile, TraceReplay, bundled_profiles, load_profile
from link_emulator.relay import LinkRelay
from link_emulator.v2v_relay import V2vRelay
from link_emulator.validate import P50_Z, Settings, validate_direction


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the link emulator's options to ``parser``."""
    parser.add_argument(
        "--config", metavar="FILE", help="YAML file with LinkConfig fields; the options below override it"
    )
    parser.add_argument("--link-id", help="link name used in v2x/link/{link_id}/stats (default link1)")
    parser.add_argument("--site", metavar="FILE", help="site file (site.yaml): its RSU's position (--rsu-id, or "
                        "the site's only RSU) is rsu_position, so that the channel depends on the vehicle's distance")
    parser.add_argument("--rsu-id", help="with --site: the RSU of the site this link serves")
    parser.add_argument("--vehicle-id", help="with --vehicle-connect: the vehicle whose ego poses set the RSU "
                        "distance (default: the first one heard; poses of others, and implausible jumps, are refused)")
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
        help="Zenoh endpoint of the vehicle side, e.g. tcp/127.0.0.1:7448 (repeatable; one vehicle)",
    )
    parser.add_argument(
        "--vehicle",
        metavar="ID=EP[,EP]",
        dest="vehicles",
        action="append",
        type=parse_vehicle,
        help=f"a vehicle served on its own session and channel: its id and the Zenoh endpoint(s) of its side, "
        f"e.g. car1=tcp/127.0.0.1:7448 (repeatable, at most {MAX_VEHICLES}; instead of --vehicle-connect)",
    )
    parser.add_argument("--v2v", action="store_true", default=None,
                        help="V2V mode: no RSU side; relay each --vehicle's v2x/v2v/<id>/** to every other vehicle, "
                        "through a channel per ordered vehicle pair (at least two --vehicle)")
    parser.add_argument(
        "--profile",
        metavar="NAME|PATH",
        help="bundled link profile (see --list-profiles) or a profile YAML file (default lte-v2x)",
    )
    parser.add_argument("--seed", type=int, help="seed of the delay and loss draws (default 0)")
    parser.add_argument(
        "--control-listen",
        metavar="EP",
        action="append",
        help="also listen on this Zenoh endpoint (vehicle-side session) for link controllers such as "
        "'v2i link set' (repeatable); LinkControl messages on v2x/link/{link_id}/control are applied",
    )
    parser.add_argument("--pki", metavar="DIR", help="site PKI directory (v2i pki): apply only link control signed "
                        "by an operator certificate of its CA, fresh (<= 2 s old, <= 0.5 s ahead by this host's "
                        "clock) and not replayed; rejections are counted by reason in the stats")
    parser.add_argument("--insecure-control", action="store_true", default=None,
                        help="lab only: apply unsigned link control (without --pki and without this, every "
                        "control is refused as 'unauthenticated')")
    parser.add_argument(
        "--duration",
        metavar="S",
        type=positive_seconds,
        help="exit cleanly after S seconds (default: run until SIGINT or SIGTERM)",
    )
    parser.add_argument("--list-profiles", action="store_true", help="print the bundled profile names and exit")
    add_metrics_options(parser)
    sub = parser.add_subparsers(dest="link_command", metavar="{validate,set}", required=False)
    text = "push N messages through a profile's channel model and compare with what it declares"
    configure_validate_parser(sub.add_parser("validate", help=text, description=text))
    text = "change a running link emulator: switch its profile, clear or add an impairment"
    configure_set_parser(sub.add_parser("set", help=text, description=SET_DESCRIPTION,
                                        formatter_class=argparse.RawDescriptionHelpFormatter))


def site_rsu_position(site_path: str | None, rsu_id: str | None) -> tuple[float, float] | None:
    """The map position (m) of the RSU ``rsu_id`` of the site file (None: its only RSU); None without a
    site. ConfigError naming the file or the RSU ids there are."""
    if site_path is None:
        if rsu_id is not None:
            raise ConfigError("--rsu-id names an RSU of a site: give the site (--site FILE)")
        return None
    site = load_site(site_path)
    if rsu_id is None and len(site.rsus) != 1:
        raise ConfigError(f"site {site_path} has {len(site.rsus)} RSUs ({[r.id for r in site.rsus]}): "
                          "name this link's with --rsu-id")
    try:
        return site.rsu(rsu_id or site.rsus[0].id).xy
    except ValueError as exc:
        raise ConfigError(f"{site_path}: {exc}") from None


def parse_vehicle(text: str) -> dict[str, object]:
    """argparse type of ``--vehicle ID=EP[,EP]``: ``{"vehicle_id": ID, "connect": [EP, ...]}``.

    The id and endpoints are validated with the rest of the config (``LinkConfig``).
    """
    vehicle_id, sep, endpoints = text.partition("=")
    connect = [ep.strip() for ep in endpoints.split(",") if ep.strip()]
    if not sep or not vehicle_id.strip() or not connect:
        raise argparse.ArgumentTypeError(f"expected ID=EP[,EP], e.g. car1=tcp/127.0.0.1:7448, got {text!r}")
    return {"vehicle_id": vehicle_id.strip(), "connect": connect}


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


def run(args: argparse.Namespace) -> int:
    """Run the emulator until signalled (or ``--duration``).

    Returns 0 on a clean stop, 2 on a bad config or profile, 1 when Zenoh cannot start.
    """
    limit_malloc_arenas()
    if args.list_profiles:
        print("\n".join(bundled_profiles()))
        return 0
    overrides = {
        "link_id": args.link_id,
        "rsu_connect": args.rsu_connect,
        "vehicle_connect": args.vehicle_connect,
        "profile": args.profile,
        "seed": args.seed,
        "control_listen": args.control_listen,
        "vehicle_id": args.vehicle_id,
        "vehicles": args.vehicles,
        "v2v": args.v2v,
        "pki": args.pki,
        "insecure_control": args.insecure_control,
    }
    try:
        overrides["rsu_position"] = site_rsu_position(args.site, args.rsu_id)
        config = load_config(LinkConfig, args.config, overrides)
        relay = V2vRelay(config, SystemClock()) if config.v2v else LinkRelay(config, SystemClock())
        server = metrics_server(relay, "link", args)  # /metrics with --metrics-port
    except (ConfigError, MetricsPortError, PkiError) as exc:
        print(f"link emulator: {exc}", file=sys.stderr)
        return 2
    name = f"link {config.link_id}"  # in its log lines, its relay's warnings too
    logging.basicConfig(level=logging.WARNING, format=f"[{name}] %(message)s")
    log(name, relay.control_auth.describe())
    freeze_heap()
    stop = threading.Event()
    try:
        with _stop_on_signals(stop), _stop_after(stop, args.duration):
            try:
                relay.open()
            except zenoh.ZError as exc:
                print(f"link emulator: cannot open Zenoh sessions: {exc}", file=sys.stderr)
                return 1
            _print_ready(config.link_id, [side.vehicle_id for side in config.vehicle_sides()])
            relay.run(stop)
    finally:
        if server is not None:
            server.close()
    return 0


def run_validate(args: argparse.Namespace) -> int:
    """``v2i link validate``: 0 when done (with ``--check``: 1 when a check fails), 2 on bad input."""
    try:
        name, direction = _validated_direction(args)
        if args.size_bytes < 0 or not args.interval_ms > 0.0:
            raise ValueError("--size-bytes must be >= 0 and --interval-ms > 0")
    except (ConfigError, ValueError) as exc:
        print(f"link validate: {one_line_error(exc)}", file=sys.stderr)
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
    low, high = report["p50_range_ms"]
    lines.append(f"p50 accepted in [{_fmt(low)}, {_fmt(high)}] ms: {P50_Z:g} standard errors of a median "
                 f"of {report['effective_samples']:.0f} independent draws")
    lines.append(f"overtaken by a later-sent message: {100.0 * report['overtaken_ratio']:.4f} % of deliveries")
    if "ks_statistic" in report:
        lines.append(f"KS statistic (achieved vs trace delays): {_fmt(report['ks_statistic'])}")
    checks = ", ".join(f"{name} {'ok' if ok else 'FAILED'}" for name, ok in report["checks"].items())
    lines.append(f"checks: {checks}")
    return "\n".join(lines)


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"


def _print_ready(link_id: str, vehicle_ids: list[str | None]) -> None:
    """The one machine-readable line telling supervisors that the relay is up (and for whom)."""
    print(json.dumps({"event": "ready", "service": "link", "link_id": link_id, "vehicles": vehicle_ids}), flush=True)


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
