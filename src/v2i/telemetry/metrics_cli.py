"""``--metrics-port`` / ``--metrics-address`` of the services, and the node wrapper that serves them.

Kept apart from ``v2i.telemetry.prometheus`` so that parsing a service's options (``v2i obu --help``)
does not import ``prometheus_client``; the exporter is imported only when a port is given.
"""

from __future__ import annotations

import argparse
import threading
from typing import Any

from v2i.telemetry.metrics_port import DEFAULT_ADDRESS, MetricsPortError  # noqa: F401 (MetricsPortError: re-exported)


def add_metrics_options(p: argparse.ArgumentParser) -> None:
    """``--metrics-port`` and ``--metrics-address`` (the service's /metrics endpoint)."""
    p.add_argument("--metrics-port", type=_port, metavar="PORT", default=0,
                   help="serve Prometheus metrics on http://ADDRESS:PORT/metrics (v2i_* series); 0: off (default)")
    p.add_argument("--metrics-address", metavar="ADDRESS", default=DEFAULT_ADDRESS,
                   help="address the metrics endpoint listens on (default %(default)s: this host only; "
                        "0.0.0.0 in a container, for a Prometheus server on another host)")


def _port(text: str) -> int:
    value = int(text)
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be a TCP port 0..65535, got {text}")
    return value


class ExportedNode:
    """A service node whose ``/metrics`` server closes when ``run`` returns (``run_service``'s node)."""

    def __init__(self, node: Any, server: Any) -> None:
        self.node, self.server = node, server

    def run(self, stop: threading.Event) -> None:
        try:
            self.node.run(stop)
        finally:
            if self.server is not None:
                self.server.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.node, name)


def metrics_server(node: Any, service: str, args: argparse.Namespace) -> Any:
    """The ``/metrics`` server of ``node`` (``service``: rsu, obu, link) when ``args.metrics_port``
    asks for one, else None; MetricsPortError (a ValueError) when the port cannot be had."""
    port = getattr(args, "metrics_port", 0)
    if not port:
        return None
    from v2i.telemetry.prometheus import serve
    from v2i.telemetry.prometheus_collectors import collector_for

    return serve(collector_for(service, node), port, getattr(args, "metrics_address", DEFAULT_ADDRESS))


def export_node(node: Any, service: str, args: argparse.Namespace) -> Any:
    """``node`` with its ``/metrics`` served (closed when its ``run`` returns) when ``args.metrics_port``
    asks, else ``node`` itself; MetricsPortError when the port cannot be had."""
    server = metrics_server(node, service, args)
    return node if server is None else ExportedNode(node, server)
