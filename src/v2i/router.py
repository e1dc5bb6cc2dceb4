"""``v2i router``: a Zenoh router, so that the nodes of a large site meet through routers
instead of a full mesh of peers.

Zenoh 1.10 routers forward for their *clients* only: two peers attached to one router reach
each other only over a direct connection (failover brokering between peers is gone), so the
services behind a router run as clients (``V2I_ZENOH_MODE=client``, see
``v2i.runtime.transport``). Scouting and gossip are off, as in every v2i session, unless a
``--config`` file turns them on; routers meet only through ``--connect`` endpoints.

The process follows the services' conventions (``v2i.runtime.process``): one JSON ready line on
stdout once the router listens, human lines on stderr (each client, peer or router that
connects or leaves), clean exit on SIGINT / SIGTERM or after ``--duration`` seconds.
"""

from __future__ import annotations

import argparse
import json
import queue
import threading
import time
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

# Zenoh's own router port; a router given no endpoint at all listens here on every interface.
DEFAULT_LISTEN = ("tcp/[::]:7447",)
POLL_S = 0.2  # the loop's wake-up period: stop and duration are checked this often
FLAG_OF_FIELD = {"listen": "--listen", "connect": "--connect", "zenoh_config": "--config", "duration_s": "--duration"}


class RouterConfig(BaseModel):
    """What ``v2i router`` was asked for; endpoints given here replace those of ``zenoh_config``."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    listen: list[str] = Field(default_factory=list)
    connect: list[str] = Field(default_factory=list, description="other routers (router-to-router)")
    zenoh_config: Path | None = Field(None, description="a Zenoh JSON5 configuration file")
    duration_s: float | None = Field(None, gt=0, description="default: until SIGINT / SIGTERM")


def zenoh_router_config(config: RouterConfig):
    """The ``zenoh.Config`` of the router and the endpoints it will listen on and connect to.

    Without a file: ``v2i.runtime.transport.session_config`` in router mode (no scouting, gossip or
    shared memory, v2i's message size bound), listening on ``DEFAULT_LISTEN`` when no endpoint
    is given. With a file: the file, in router mode (ValueError when it names another mode),
    with scouting and gossip off where it leaves them unset, and the CLI endpoints in place of
    its own. Returns ``(zenoh.Config, listen, connect)``.
    """
    import zenoh

    from v2i.runtime.transport import read_config_file, session_config

    if config.zenoh_config is None:
        listen = config.listen or ([] if config.connect else list(DEFAULT_LISTEN))
        return session_config(listen, config.connect, mode="router"), listen, list(config.connect)
    conf = read_config_file(config.zenoh_config)
    mode = json.loads(conf.get_json("mode"))
    if mode not in (None, "router"):
        raise ValueError(f"{config.zenoh_config}: mode is {mode!r}; v2i router runs a Zenoh router (mode: router)")
    conf.insert_json5("mode", '"router"')
    for key in ("scouting/multicast/enabled", "scouting/gossip/enabled"):
        if json.loads(conf.get_json(key)) is None:
            conf.insert_json5(key, "false")
    for key, endpoints in (("listen/endpoints", config.listen), ("connect/endpoints", config.connect)):
        if endpoints:
            conf.insert_json5(key, json.dumps(endpoints))
    return conf, _router_endpoints(conf, "listen"), _router_endpoints(conf, "connect")


def _router_endpoints(conf, kind: str) -> list[str]:
    """``listen`` / ``connect`` endpoints of a router config (a list, or a per-mode map)."""
    endpoints = json.loads(conf.get_json(f"{kind}/endpoints"))
    if isinstance(endpoints, dict):
        endpoints = endpoints.get("router", [])
    return [e if isinstance(e, str) else json.dumps(e) for e in endpoints or []]


class RouterNode:
    """The router's session and its loop: logs transport events until stopped."""

    def __init__(self, config: RouterConfig, clock_s=time.monotonic):
        self.config = config
        self._clock_s = clock_s
        self.zenoh_config, self.listen, self.connect = zenoh_router_config(config)
        if not self.listen and not self.connect:
            raise ValueError("the router neither listens nor connects: give --listen EP or --connect EP")
        self._events: queue.Queue = queue.Queue()  # (opened: bool, whatami: str, zid: str), from Zenoh's thread
        self.connected: dict[str, str] = {}  # zid -> whatami, as this loop last heard
        self.sessions_seen = 0

    def run(self, stop: threading.Event) -> None:
        import zenoh

        from v2i.runtime.process import announce, log

        self._opened_kind = zenoh.SampleKind.PUT  # a transport event of this kind opened; DELETE: closed
        session = zenoh.open(self.zenoh_config)
        listener = None
        try:
            listener = session.info.declare_transport_events_listener(self._on_transport_event, history=True)
            announce("ready", "router", zid=str(session.zid()), listen=self.listen, connect=self.connect)
            log("router", f"ready: zid {session.zid()}, listening on {', '.join(self.listen) or '-'}, "
                          f"connecting to {', '.join(self.connect) or '-'}")
            self._loop(stop)
        finally:
            if listener is not None:
                listener.undeclare()
            session.close()
            log("router", f"stopped: {self.sessions_seen} sessions seen, {len(self.connected)} still connected")

    def _on_transport_event(self, event) -> None:
        """Zenoh callback: enqueue only."""
        transport = event.transport
        self._events.put((event.kind == self._opened_kind, str(transport.whatami).lower(), str(transport.zid)))

    def _loop(self, stop: threading.Event) -> None:
        end_s = None if self.config.duration_s is None else self._clock_s() + self.config.duration_s
        while not stop.is_set() and (end_s is None or self._clock_s() < end_s):
            try:
                self._note(*self._events.get(timeout=POLL_S))
            except queue.Empty:
                continue

    def _note(self, opened: bool, whatami: str, zid: str) -> None:
        from v2i.runtime.process import log

        if opened:
            self.sessions_seen += zid not in self.connected
            self.connected[zid] = whatami
        else:
            self.connected.pop(zid, None)
        kinds = {k: sum(1 for w in self.connected.values() if w == k) for k in ("client", "peer", "router")}
        log("router", f"{whatami} {zid} {'connected' if opened else 'left'}; now "
                      + ", ".join(f"{k}s {n}" for k, n in kinds.items()))


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Zenoh router for sites with many RSUs and vehicles: the services connect to it as clients "
        "(V2I_ZENOH_MODE=client) instead of forming a mesh of peers. Keep one router on the RSU side "
        "and one on the vehicle side, never connected to each other, with the link emulator attached "
        "to both: it stays the only path between RSUs and vehicles (deploy/README.md)."
    )
    p.add_argument("--listen", action="append", metavar="EP",
                   help=f"Zenoh endpoint to listen on (repeatable; default {DEFAULT_LISTEN[0]} without any endpoint)")
    p.add_argument("--connect", action="append", metavar="EP", help="another router to connect to (repeatable)")
    p.add_argument("--config", dest="zenoh_config", metavar="FILE",
                   help="Zenoh JSON5 configuration (e.g. deploy/router.json5); --listen / --connect replace its "
                        "endpoints, scouting and gossip stay off unless it turns them on")
    p.add_argument("--duration", dest="duration_s", type=float, metavar="S", help="seconds to run (default: until stopped)")


def run(args: argparse.Namespace) -> int:
    """``v2i router``: 0 after a clean stop, 2 (one stderr line) when the config or Zenoh refuses."""
    import sys

    import zenoh
    from pydantic import ValidationError

    from v2i.runtime.config import one_line_error
    from v2i.runtime.process import limit_malloc_arenas, stop_on_signals, zenoh_problem

    limit_malloc_arenas()
    fields = {f: getattr(args, f) for f in RouterConfig.model_fields if getattr(args, f, None) is not None}
    try:
        node = RouterNode(RouterConfig(**fields))
    except (ValidationError, ValueError, OSError) as exc:
        print(f"v2i router: {one_line_error(exc, FLAG_OF_FIELD)}", file=sys.stderr)
        return 2
    except zenoh.ZError as exc:  # the configuration file
        print(f"v2i router: {args.zenoh_config}: {zenoh_problem(exc)}", file=sys.stderr)
        return 2
    try:
        node.run(stop_on_signals())
    except zenoh.ZError as exc:
        where = f"listen {', '.join(node.listen) or '-'}; connect {', '.join(node.connect) or '-'}"
        print(f"v2i router: Zenoh: {zenoh_problem(exc)} ({where})", file=sys.stderr)
        return 2
    return 0
