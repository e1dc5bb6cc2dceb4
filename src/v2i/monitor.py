"""``v2i monitor``: a live terminal dashboard of a running site, or one JSON snapshot.

One Zenoh session per ``--connect`` endpoint (scouting and gossip off, as every v2i session;
one session per endpoint so that the monitor never joins the RSU side to the vehicle side behind
the link emulator's back). Each subscribes ``v2x/**/metrics`` and ``v2x/link/*/stats``; the
callbacks only enqueue ``(source, key, payload, receive time)`` in a bounded queue (a full one
drops, counted), and the main loop feeds ``v2i.telemetry.snapshot.TelemetryBoard`` and draws
``v2i.monitor_view`` with ``rich`` at ``--refresh-hz``, or with ``--once`` prints one snapshot.
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import time
from dataclasses import dataclass
from typing import Any

SUBSCRIPTIONS = ("v2x/**/metrics", "v2x/link/*/stats")
QUEUE_MESSAGES = 10_000  # received, not yet fed to the board (~10 s of a 20-vehicle site)
LINK_GRACE_S = 1.2  # --once: after every side's metrics, wait this long for a link's stats (1 s period)
RSU_GRACE_S = 3.0  # --once: ... and this long for each vehicle's first RSU list, when an RSU is heard
METRIC_KINDS = ("obu_metrics", "rsu_metrics", "link_stats")  # what a side must have delivered for --once


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Live dashboard of a running v2i site, refreshed several times a second: per vehicle the output "
        "and RSU deadline-miss ratios (whole run and last --window-s seconds), the fusion mode and mode "
        "shares, per RSU the one-way delay p50/p95, loss, data age and clock offset +- uncertainty; the "
        "RSUs' lists and refusals; each link emulator's counters and impairments in force; rejected "
        "inputs by reason. A Zenoh peer does not forward between the peers it meets, so connect to each "
        "service whose messages you want: the OBU's endpoint (its --listen) for v2x/obu/*/metrics, the "
        "RSU's for v2x/rsu/*/metrics (they stay on the RSU's side of the link), and the link emulator's "
        "control endpoint (its --control-listen) for v2x/link/*/stats; behind a v2i router, the router. "
        "v2i demo logs all three: v2i monitor --connect <OBU> --connect <RSU> --connect <link>. Each "
        "endpoint gets its own session: the monitor never bridges the RSU and vehicle sides.")
    p.add_argument("--connect", action="append", required=True, metavar="EP",
                   help="Zenoh endpoint of a service, e.g. tcp/127.0.0.1:7447 (repeatable)")
    p.add_argument("--once", action="store_true",
                   help="wait until every endpoint delivered metrics or link stats (then up to 1.2 s more for a "
                        "link's stats if none came yet, and up to 3 s for each vehicle to hear an RSU when an "
                        "RSU's metrics came), print one snapshot and exit; exit 1 when an endpoint delivered "
                        "neither within --timeout. A vehicle that heard no RSU yet is shown so (rsu_heard false, "
                        "rsus empty)")
    p.add_argument("--json", metavar="PATH", help="with --once: write the snapshot as JSON to PATH ('-': stdout; "
                   "keys documented in telemetry/snapshot.py); without it --once prints the tables")
    p.add_argument("--timeout", type=float, default=5.0, metavar="S",
                   help="with --once: seconds to wait for metrics (default %(default)s)")
    p.add_argument("--refresh-hz", type=float, default=4.0, help="dashboard refreshes per second (default %(default)s)")
    p.add_argument("--window-s", type=float, default=10.0,
                   help="the recent window of the ratios, seconds (default %(default)s)")
    p.add_argument("--duration", type=float, metavar="S", help="live view: stop after S seconds (default: Ctrl-C)")


@dataclass
class Source:
    """One connected endpoint: its session and what came from it."""

    endpoint: str
    session: Any
    metrics: int = 0  # obu_metrics, rsu_metrics and link_stats fed to the board
    messages: int = 0

    def view(self) -> dict[str, Any]:
        return {"endpoint": self.endpoint, "connected": bool(list(self.session.info.peers_zid())),
                "messages": self.messages, "metrics_messages": self.metrics}


class Monitor:
    """The sessions, the inbox and the board; ``pump`` feeds what arrived so far."""

    def __init__(self, endpoints: list[str], window_s: float):
        from v2i.telemetry.snapshot import TelemetryBoard

        self.board = TelemetryBoard(window_s=window_s)
        self.sources: list[Source] = []
        self.inbox: queue.Queue = queue.Queue(maxsize=QUEUE_MESSAGES)
        self.dropped = 0
        self._subscribers: list = []
        self.endpoints = endpoints

    def open(self) -> None:
        from v2i.runtime.transport import open_session

        for index, endpoint in enumerate(self.endpoints):
            session = open_session(connect=[endpoint])
            self.sources.append(Source(endpoint, session))
            for key in SUBSCRIPTIONS:
                self._subscribers.append(session.declare_subscriber(key, lambda s, i=index: self._on_sample(i, s)))

    def _on_sample(self, index: int, sample) -> None:
        """Zenoh callback: stamp and enqueue only."""
        try:
            self.inbox.put_nowait((index, str(sample.key_expr), sample.payload.to_bytes(), time.monotonic_ns()))
        except queue.Full:
            self.dropped += 1  # one writer per source thread; a lost increment only undercounts

    def pump(self, wait_s: float = 0.0) -> None:
        """Feed every queued message to the board, waiting up to ``wait_s`` for the first."""
        try:
            item = self.inbox.get(timeout=wait_s) if wait_s > 0 else self.inbox.get_nowait()
        except queue.Empty:
            return
        while item is not None:
            index, key, payload, receive_ns = item
            kind = self.board.on_sample(key, payload, receive_ns)
            source = self.sources[index]
            source.messages += 1
            source.metrics += kind in METRIC_KINDS
            try:
                item = self.inbox.get_nowait()
            except queue.Empty:
                item = None

    def snapshot(self) -> dict[str, Any]:
        snap = self.board.snapshot(time.monotonic_ns())
        snap["sources"] = [s.view() for s in self.sources]
        snap["intake"]["dropped_queue_full"] = self.dropped
        return snap

    def close(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()
        for source in self.sources:
            source.session.close()


def still_waiting(board, waited_s: float) -> bool:
    """``--once``, once every endpoint delivered, ``waited_s`` later: True while a link's stats are
    missing (up to ``LINK_GRACE_S``) or, when an RSU's metrics came, a vehicle has heard no RSU
    yet (up to ``RSU_GRACE_S``: its first lists are on their way)."""
    no_link = not board.links and waited_s < LINK_GRACE_S
    deaf = bool(board.rsus) and any(not v.hears_rsu() for v in board.vehicles.values()) and waited_s < RSU_GRACE_S
    return no_link or deaf


def run_once(monitor: Monitor, timeout_s: float, json_path: str | None) -> int:
    """Wait for metrics or stats from every endpoint (then briefly for link stats); print one snapshot."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not all(s.metrics for s in monitor.sources):
        monitor.pump(wait_s=0.05)
    silent = [s.endpoint for s in monitor.sources if not s.metrics]
    if silent:
        why = "; ".join(f"{s.endpoint}: {'connected, no metrics' if s.view()['connected'] else 'not connected'}"
                        for s in monitor.sources if not s.metrics)
        print(f"v2i monitor: no metrics or link stats within {timeout_s:g} s from {', '.join(silent)} ({why}); "
              "is a v2i service listening there? (an OBU's or RSU's --listen, a link emulator's --control-listen)",
              file=sys.stderr)
        return 1
    grace_start = time.monotonic()
    while time.monotonic() < deadline and still_waiting(monitor.board, time.monotonic() - grace_start):
        monitor.pump(wait_s=0.05)
    snap = monitor.snapshot()
    deaf = [vid for vid, v in snap["vehicles"].items() if not v["rsu_heard"]]
    if deaf:
        print(f"v2i monitor: {', '.join(deaf)} heard no RSU yet (no RSU list accepted so far); the snapshot says so: "
              "rsu_heard false, no RSU rows", file=sys.stderr)
    if json_path == "-":
        print(json.dumps(snap, indent=2))
    elif json_path:
        with open(json_path, "w") as out:
            out.write(json.dumps(snap, indent=2) + "\n")
    else:
        from rich.console import Console

        from v2i.monitor_view import dashboard

        Console().print(dashboard(snap, snap["sources"]))
    return 0


def run_live(monitor: Monitor, refresh_hz: float, duration_s: float | None) -> int:
    """The dashboard, redrawn ``refresh_hz`` times a second until Ctrl-C or ``duration_s``."""
    from rich.live import Live

    from v2i.monitor_view import dashboard

    period_s = 1.0 / refresh_hz
    end = None if duration_s is None else time.monotonic() + duration_s
    snap = monitor.snapshot()
    with Live(dashboard(snap, snap["sources"]), refresh_per_second=refresh_hz, screen=False,
              redirect_stderr=False) as live:
        while end is None or time.monotonic() < end:
            next_draw = time.monotonic() + period_s
            while (left := next_draw - time.monotonic()) > 0:
                monitor.pump(wait_s=min(left, 0.05))
            snap = monitor.snapshot()
            live.update(dashboard(snap, snap["sources"]))
    return 0


def run(args: argparse.Namespace) -> int:
    """``v2i monitor``: 0 when done (Ctrl-C in the live view), 1 when --once got no metrics, 2 on bad input."""
    import zenoh

    from v2i.runtime.process import zenoh_problem

    for flag, value in (("--timeout", args.timeout), ("--refresh-hz", args.refresh_hz), ("--window-s", args.window_s),
                        ("--duration", args.duration)):
        if value is not None and not 0 < value < float("inf"):
            print(f"v2i monitor: {flag} must be a finite number > 0, got {value:g}", file=sys.stderr)
            return 2
    if args.json and not args.once:
        print("v2i monitor: --json goes with --once (one snapshot)", file=sys.stderr)
        return 2
    monitor = Monitor(args.connect, args.window_s)
    try:
        monitor.open()
        if args.once:
            return run_once(monitor, args.timeout, args.json)
        return run_live(monitor, args.refresh_hz, args.duration)
    except zenoh.ZError as exc:
        print(f"v2i monitor: Zenoh: {zenoh_problem(exc)} (connect {', '.join(args.connect)})", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0
    finally:
        monitor.close()
