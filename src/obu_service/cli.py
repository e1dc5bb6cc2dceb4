"""``v2i obu``: run the on-board unit service."""

from __future__ import annotations

import argparse

from schemas.runtime import add_service_options, run_service

from .config import ObuConfig
from .pipeline import COMPENSATIONS, FUSION_METHODS, FUSION_MODES


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.description = (
        "On-board unit: estimates the RSU clock offset from time queries, receives RSU object "
        "lists, moves them into its own frame and time, fuses them with its own LiDAR objects and "
        "publishes the fused list on v2x/obu/{id}/objects every 10 Hz cycle, RSU data or not."
    )
    add_service_options(p, "ObuConfig", "tcp/0.0.0.0:7448", "LiDAR and localisation noise")
    p.add_argument("--vehicle-id", help="vehicle id used in key expressions (default ego)")
    p.add_argument("--connect", action="append", metavar="EP",
                   help="Zenoh endpoint to connect to, e.g. the RSU's when no link emulator is used (repeatable)")
    p.add_argument("--fusion", choices=FUSION_METHODS, help="fusion method (default kf)")
    p.add_argument("--fusion-mode", choices=FUSION_MODES,
                   help="intra | inter | planning | vehicle-only, or adaptive: the most accurate feasible mode "
                        "per cycle given the measured latency and the deadline (default adaptive)")
    p.add_argument("--compensation", choices=COMPENSATIONS,
                   help="RSU delay compensation (default predict); oosm needs --fusion kf")
    p.add_argument("--deadline-ms", type=float, help="end-to-end deadline per cycle from LiDAR capture (default 100)")
    p.add_argument("--output-interval-ms", type=float, help="longest allowed gap between two outputs (default 150)")
    p.add_argument("--sync-rate-hz", type=float, help="time-sync exchanges per second (default 10)")


def run(args: argparse.Namespace) -> int:
    def make_node(config: ObuConfig):
        from .node import ObuNode

        return ObuNode(config)

    return run_service("obu", ObuConfig, args, make_node)
