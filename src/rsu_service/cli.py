"""``v2i rsu``: the roadside unit service's options, and its run with a node the composition root
makes (``v2i.services.rsu_node``: the site, source and clock model a configuration names)."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from schemas.list_wire import WIRES
from v2i.runtime.process import add_service_options, run_service
from v2i.telemetry.metrics_cli import add_metrics_options, export_node

from rsu_service.config import PREDICTORS, SOURCES, RsuConfig


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Roadside unit: perceives the scenario with its (simulated) camera, tracks, and publishes "
        "timestamped object lists on v2x/rsu/{id}/objects; answers NTP-style time queries on "
        "v2x/rsu/{id}/time. Its clock can be offset, drifting and stepped on purpose."
    )
    add_service_options(p, "RsuConfig", "tcp/0.0.0.0:7447", "camera noise")
    p.add_argument("--site", metavar="FILE",
                   help="site file (site.yaml: RSUs, vehicles, map origin, map) instead of a scenario, with "
                        "--source zenoh or video: no scenario and no simulator is loaded; without --duration the "
                        "RSU runs until stopped")
    p.add_argument("--rsu-id", help="RSU id used in key expressions and, by default, the --pki certificate it signs "
                   "with (default rsu1); it runs the site's RSU of that id, or a single-RSU site's only RSU whatever "
                   "the id. An OBU registers it when its site lists the id, its --pki holds this RSU's certificate "
                   "and the site places it, or it is in the OBU's --known-rsus")
    p.add_argument("--connect", action="append", metavar="EP", help="Zenoh endpoint to connect to (repeatable)")
    p.add_argument("--clock-offset-ms", type=float, help="RSU clock offset from true time, ms")
    p.add_argument("--clock-drift-ppm", type=float, help="RSU clock drift, ppm")
    p.add_argument("--clock-step-ms", type=float, help="RSU clock step size, ms (with --clock-step-at-s)")
    p.add_argument("--clock-step-at-s", type=float, help="scenario time of the RSU clock step, s")
    p.add_argument("--predictor", choices=PREDICTORS,
                   help="5 s paths on v2x/rsu/{id}/predictions: lane-following on the site's Lanelet2 map, "
                        "constant velocity, or auto (lane when a map exists; default)")
    p.add_argument("--source", choices=SOURCES,
                   help="perception: sim (the scenario's camera noise model; default), camera (the scenario "
                        "rendered, through the ONNX detector and the calibration), video (--video through the same), "
                        "zenoh (SensorObjects received on v2x/sensor/rsu/{id}/objects, e.g. from v2i world)")
    p.add_argument("--video", metavar="PATH", help="with --source video: a video file or a folder of PNG/JPEG frames")
    p.add_argument("--rate-hz", type=float, help="with --source video: frames per second (default: the video's); "
                   "with --source camera: the camera's rate (default: the scenario's RSU rate)")
    p.add_argument("--image-features", action="store_true", default=None,
                   help="with --source camera|video: also publish each frame's detection boxes and the ORB "
                        "keypoints + descriptors inside them on v2x/rsu/{id}/image_features, for image-level "
                        "fusion on the OBU (v2i obu --fusion roif; Maqsud's ROIF thesis)")
    p.add_argument("--image-features-max", type=int, metavar="N",
                   help="ORB keypoints per frame at most in image_features (default 1000: ~42 kB a frame)")
    p.add_argument("--model", metavar="ONNX",
                   help="detector model, YOLOv8/v5 export layout, e.g. a COCO YOLOv8n export for real images "
                   "(default: the shipped one, trained on rendered frames of the bundled scenes only)")
    p.add_argument("--calibration", metavar="FILE",
                   help="camera calibration from `v2i camera calibrate` (default: the scenario's shipped one)")
    p.add_argument("--score-threshold", type=float, help="detector score threshold (default 0.4)")
    p.add_argument("--detector-threads", type=int, help="ONNX Runtime threads (default: its own choice)")
    p.add_argument("--wire", choices=WIRES,
                   help="object list encoding: v2i (the project's compact msgpack columns on v2x/rsu/{id}/objects; "
                        "default), cpm (ETSI collective perception message, UPER, on v2x/rsu/{id}/cpm) or sdsm "
                        "(a sensor data sharing message with SAE J3224's fields and resolution, UPER, on "
                        "v2x/rsu/{id}/sdsm, but not J3224's bytes: a decoder generated from the J3224-2024 ASN.1 reads "
                        "none of them, v2i reads only its own, no other stack was tried; docs/messages.md); a v2i OBU "
                        "fuses all three, at the standard's resolution")
    p.add_argument("--cpm-rules", action="store_true", default=None,
                   help="with --wire cpm: ETSI TS 103 324 generation rules: an object goes when new, moved > 4 m, its "
                        "speed changed > 0.5 m/s or its heading > 4 degrees since last sent, or 1 s after; pedestrians "
                        "and cyclists all together every 500 ms; a CPM at most every 100 ms and at least every 1 s; a "
                        "CPM over --cpm-mtu-bytes split into segments (segmentationInfo). Default: every object in "
                        "every list, one CPM")
    p.add_argument("--cpm-mtu-bytes", type=int, metavar="N",
                   help="with --cpm-rules: the largest CPM; larger ones are segmented (default 1100)")
    p.add_argument("--predict-ahead", action="store_true", default=None,
                   help="track-predict compensation: publish tracks predicted to the publish time, "
                        "and once more half a frame later (5 Hz camera -> 10 Hz lists)")
    p.add_argument("--pki", dest="pki_dir", metavar="DIR",
                   help="site PKI directory (v2i pki site|issue): sign every object list, prediction list, image "
                        "features message and time reply (ECDSA P-256 or Ed25519, the certificate's digest, the "
                        "generation time; the full certificate once a second) as --identity")
    p.add_argument("--identity", help="certificate subject to sign as (default: the RSU id)")
    p.add_argument("--save-wire", metavar="DIR",
                   help="save every object list this RSU sends, exactly as sent in its --wire (before any --pki "
                        "signature), one file per list: DIR/<rsu-id>/NNNNNN.v2i.msgpack | .cpm.uper | .sdsm.uper, "
                        "NNNNNN counting the lists in send order (continued after files already there); the folder is "
                        "created, an unwritable one refused at start, a failed write counted and logged once")
    add_metrics_options(p)


def run(args: argparse.Namespace, make_node: Callable[[RsuConfig], object]) -> int:
    """``v2i rsu``: the node ``make_node`` makes of the configuration, run until its end or a signal."""
    return run_service("rsu", RsuConfig, args, lambda config: export_node(make_node(config), "rsu", args))
