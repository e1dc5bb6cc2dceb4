"""``v2i obu``: the on-board unit service's options, and its run with a node the composition root
makes (``v2i.services.obu_node``: the site, own sensing or camera a configuration names)."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping

from v2i.runtime.process import add_service_options, log, run_service
from v2i.security.pki_registry import unregistered_warnings
from v2i.telemetry.metrics_cli import add_metrics_options, export_node

from obu_service.config import ObuConfig
from obu_service.pipeline import COMPENSATIONS, FUSION_METHODS, FUSION_MODES


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.description = (
        "On-board unit: estimates the RSU clock offset from time queries, receives RSU object "
        "lists, moves them into its own frame and time, fuses them with its own LiDAR objects and "
        "publishes the fused list on v2x/obu/{id}/objects every 10 Hz cycle, RSU data or not."
    )
    add_service_options(p, "ObuConfig", "tcp/0.0.0.0:7448", "LiDAR and localisation noise")
    p.add_argument("--site", metavar="FILE",
                   help="site file (site.yaml: RSUs, vehicles, map origin, map) instead of a scenario, with "
                        "--source zenoh: no scenario and no simulator is loaded; without --duration the OBU runs "
                        "until stopped")
    p.add_argument("--vehicle-id", help="vehicle id used in key expressions (default ego)")
    p.add_argument("--connect", action="append", metavar="EP",
                   help="Zenoh endpoint to connect to, e.g. the RSU's when no link emulator is used (repeatable)")
    p.add_argument("--source", choices=("sim", "zenoh"),
                   help="own detections and pose: sim (the scenario's LiDAR and localisation; default) or zenoh "
                        "(SensorObjects and LocalizationPose received on v2x/sensor/vehicle/{id}/objects|pose, "
                        "e.g. from v2i world or examples/external_publisher.py; one cycle per detection frame, "
                        "a cycle without own objects when a frame is missing at the slot's fuse-by time)")
    p.add_argument("--fusion", choices=(*FUSION_METHODS, "roif"),
                   help="fusion method (default kf); roif: image-level fusion (Maqsud's thesis) of the ego camera (the "
                        "scenario's ego_camera, rendered, through the ONNX detector, ORB) with the RSU's "
                        "v2x/rsu/{id}/image_features (v2i rsu --source camera --image-features), published as "
                        "ImageFusedBoxes on v2x/obu/{id}/image_objects at the camera's rate")
    p.add_argument("--roif-pair-tolerance-ms", type=float,
                   help="roif: an RSU frame pairs with an ego frame whose capture time (clock-corrected) is "
                        "within this (default 50)")
    p.add_argument("--roif-wait-ms", type=float,
                   help="roif: how long an ego frame waits for its RSU partner before it goes out with the "
                        "ego's own boxes only, counted (default 300)")
    p.add_argument("--roif-deadline-ms", type=float, help="roif: ego capture -> output deadline (default 450)")
    p.add_argument("--roif-threads", type=int, help="roif: ONNX Runtime threads of the ego camera's detector")
    p.add_argument("--fusion-mode", choices=FUSION_MODES,
                   help="intra | inter | planning | vehicle-only, or adaptive: the most accurate feasible mode "
                        "per cycle given the measured latency and the deadline (default adaptive)")
    p.add_argument("--compensation", choices=COMPENSATIONS,
                   help="RSU delay compensation (default predict); oosm needs --fusion kf")
    p.add_argument("--deadline-ms", type=float, help="end-to-end deadline per cycle from LiDAR capture (default 100)")
    p.add_argument("--output-interval-ms", type=float, help="longest allowed gap between two outputs (default 150)")
    p.add_argument("--sync-rate-hz", type=float, help="time-sync exchanges per second (default 10)")
    p.add_argument("--v2v", action="store_true", default=None,
                   help="V2V: share what the own sensors perceive with peer vehicles on v2x/v2v/{id}/objects, "
                        "answer and send peer time requests, fuse peers' lists (each peer its own source slot)")
    p.add_argument("--max-peers", type=int, help="V2V peers given a fusion source slot (default 8)")
    p.add_argument("--wires", type=lambda v: tuple(w.strip() for w in v.split(",") if w.strip()), metavar="LIST",
                   help="RSU list encodings to take, comma-separated, of v2i, cpm (ETSI CPM), sdsm (SAE J3224 SDSM); "
                        "the standard ones compile their ASN.1 at start-up (default v2i)")
    p.add_argument("--pki", dest="pki_dir", metavar="DIR",
                   help="site PKI directory (v2i pki): verify RSU object lists, prediction lists and time replies "
                        "against its CA, revocation list and certificates")
    p.add_argument("--known-rsus", type=rsu_ids, metavar="ID[,ID...]",
                   help="the RSUs to register (served first by the intake, always admitted, their objects bounded "
                        "around them): each stands where the site places it (its RSU of that id, or a single-RSU "
                        "site's only RSU, as v2i rsu --rsu-id runs it). Default: the site's RSUs and, with --pki, the "
                        "RSU ids its certificates certify that the site places; the OBU logs them at start")
    p.add_argument("--security", choices=("strict", "permissive", "off"),
                   help="strict drops, and counts by reason (security_<reason> in the metrics), anything unsigned, "
                        "forged, from an unknown, revoked or expired certificate, on a key its certificate does not "
                        "cover, stale or replayed; permissive counts and fuses anyway; off unwraps without checks "
                        "(default: strict with --pki, off without)")
    add_metrics_options(p)


def rsu_ids(text: str) -> tuple[str, ...]:
    """``--known-rsus``: comma-separated ids (checked by ``ObuConfig``)."""
    return tuple(rsu_id.strip() for rsu_id in text.split(",") if rsu_id.strip())


def registration_lines(config: ObuConfig, known: Mapping[str, tuple[float, float]] | tuple[str, ...]) -> list[str]:
    """What the OBU says at start about the RSUs it registered (``known``: the pipeline's, id -> map
    position, or ids): the list, then a WARNING for each RSU its ``--pki`` certifies and it left out."""
    where = {rsu_id: f" at ({known[rsu_id][0]:g}, {known[rsu_id][1]:g})" if isinstance(known, Mapping) else ""
             for rsu_id in known}
    source = "--known-rsus" if config.known_rsus is not None else (
        "the site and the RSU certificates of --pki" if config.pki_dir else "the site")
    listed = ", ".join(f"{rsu_id}{where[rsu_id]}" for rsu_id in known) or "none"
    lines = [f"registered RSUs (from {source}; served first, always admitted): {listed}"]
    return lines + [f"WARNING: {w}" for w in unregistered_warnings(config.certified_rsus(), list(known))]


def run(args: argparse.Namespace, make_node: Callable[[ObuConfig], object]) -> int:
    """``v2i obu``: the node ``make_node`` makes of the configuration, run until its end or a signal;
    the RSUs it registered said at start (``registration_lines``)."""
    def made(config: ObuConfig):
        node = make_node(config)
        for line in registration_lines(config, node.pipeline.config.known_rsus):
            log(node.name, line)
        return export_node(node, "obu", args)

    return run_service("obu", ObuConfig, args, made)
