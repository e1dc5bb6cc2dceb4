"""Command line of the link emulator service (``v2i link ...``)."""

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
from .profile import bundled_profiles
from .relay import LinkRelay


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
