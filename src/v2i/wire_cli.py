"""``v2i wire decode FILE... [--wire cpm|sdsm|v2i] [--json PATH|-]``: what RSU object-list messages
(one message a file, as ``--save-wire`` writes them, or any third party's) say, read by v2i's codecs.

Per file one JSON line: ``{"file", "ok": true, "reference": {"lat_deg", "lon_deg", "time_tai_ms"},
"objects": [{"id", "x_m", "y_m", "vx_mps", "vy_mps", "class", ...}], ...}`` with x, y east / north
of the message's reference position in metres (a vehicle-originated CPM: in the vehicle's own
frame, x along its ``orientation_deg``, y to its left), or ``{"file", "ok": false, "reason"}``.
A v2i list has no geodetic reference (its ``map`` frame's origin is the site's): lat / lon null.
A CPM's objects whose x or y is only "out of range" are not placed: listed apart
(``objects_out_of_range``: id and the range's bounds as x_m, y_m).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from schemas import its_time
from schemas.classes import ObjectClass
from schemas.codec import MAX_MESSAGE_BYTES, CodecError
from schemas.messages import UNKNOWN_VELOCITY_VAR
from v2i.core.files import FileRefused, read_bounded

WIRES = ("cpm", "sdsm", "v2i")
WIRE_FILE_LIMIT_BYTES = MAX_MESSAGE_BYTES  # a file holds one message, and no message is larger


def _objects(cols: dict[str, np.ndarray], delta_ms: np.ndarray | None = None) -> list[dict[str, Any]]:
    """JSON rows of object columns (metres, m/s, degrees)."""
    rows = []
    for i in range(len(cols["id"])):
        known = bool(cols["cov_vxx"][i] < UNKNOWN_VELOCITY_VAR)
        cls = int(cols["cls"][i])
        row = {"id": int(cols["id"][i]), "x_m": round(float(cols["x"][i]), 3), "y_m": round(float(cols["y"][i]), 3),
               "z_m": round(float(cols["z"][i]), 3),
               "vx_mps": round(float(cols["vx"][i]), 3) if known else None,
               "vy_mps": round(float(cols["vy"][i]), 3) if known else None,
               "ax_mps2": round(float(cols["ax"][i]), 2), "ay_mps2": round(float(cols["ay"][i]), 2),
               "yaw_deg": round(float(np.degrees(cols["yaw"][i])), 2),
               "length_m": round(float(cols["length"][i]), 2), "width_m": round(float(cols["width"][i]), 2),
               "height_m": round(float(cols["height"][i]), 2),
               "class": ObjectClass(cls).name.lower() if cls in ObjectClass._value2member_map_ else str(cls),
               "age_s": round(float(cols["age_s"][i]), 3), "confidence": round(float(cols["confidence"][i]), 3)}
        if delta_ms is not None:
            row["measurement_delta_ms"] = int(delta_ms[i])
        rows.append(row)
    return rows


def _cpm(data: bytes) -> dict[str, Any]:
    from schemas import cpm

    r = cpm.read(data)
    return {"reference": {"lat_deg": r.lat_deg, "lon_deg": r.lon_deg, "time_tai_ms": r.reference_time_ms},
            "station_id": r.station_id, "originator": r.originator, "orientation_deg": r.orientation_deg,
            "segment": r.segment, "skipped": dict(r.skipped), "objects": _objects(r.columns, r.delta_ms),
            "objects_out_of_range": r.beyond}


def _sdsm(data: bytes) -> dict[str, Any]:
    from schemas import sdsm
    from schemas import standard_wire as sw

    raw = sw.asn1_decode(sw.compiled(sdsm.ASN1_FILE), "SensorDataSharingMessage", data, "sdsm")
    ref = (raw["refPos"]["lat"], raw["refPos"]["long"])
    header, cols = sdsm.decode(data, origin_e7=ref)  # x, y: offsets from the reference position
    return {"reference": {"lat_deg": ref[0] / 1e7, "lon_deg": ref[1] / 1e7,
                          "time_tai_ms": its_time.its_ms(header.capture_time_ns)}, "objects": _objects(cols)}


def _v2i(data: bytes) -> dict[str, Any]:
    from schemas import standard_wire as sw
    from schemas.list_wire import decode_list

    msg = decode_list(data, "v2i")
    return {"reference": {"lat_deg": None, "lon_deg": None, "time_tai_ms": its_time.its_ms(msg.header.capture_time_ns)},
            "rsu_id": msg.header.rsu_id, "seq": msg.header.seq, "objects": _objects(sw.columns_of(msg.objects))}


def decode_file(path: Path, wire: str) -> dict[str, Any]:
    """The JSON object of one file (module docstring)."""
    try:
        data = read_bounded(path, WIRE_FILE_LIMIT_BYTES, "message file")
    except FileRefused as exc:
        return {"file": str(path), "ok": False, "reason": f"unreadable: {exc}"}
    try:
        body = {"cpm": _cpm, "sdsm": _sdsm, "v2i": _v2i}[wire](data)
    except CodecError as exc:
        return {"file": str(path), "ok": False, "reason": f"{exc.reason}: {exc}"}
    return {"file": str(path), "ok": True, **body}


def run(args: argparse.Namespace) -> int:
    """``v2i wire decode``: one JSON line a file (``--json``), or a short line a file; exit 1 if any failed."""
    out = None if args.json is None else (sys.stdout if args.json == "-" else open(args.json, "w"))
    failed = 0
    try:
        for name in args.files:
            row = decode_file(Path(name), args.wire)
            failed += not row["ok"]
            if out is not None:
                out.write(json.dumps(row) + "\n")
            if out is not sys.stdout:
                print(f"{name}: {len(row['objects'])} objects" if row["ok"] else f"{name}: refused: {row['reason']}")
    finally:
        if out is not None and out is not sys.stdout:
            out.close()
    return 1 if failed else 0


def configure_parser(p: argparse.ArgumentParser) -> None:
    """``v2i wire``'s options: the ``decode`` sub-command."""
    sub = p.add_subparsers(dest="wire_command", required=True, metavar="{decode}")
    text = "decode RSU object-list messages, one a file (as --save-wire writes them), and print what they say"
    d = sub.add_parser("decode", help=text, description=text)
    d.add_argument("files", nargs="+", metavar="FILE")
    d.add_argument("--wire", default="cpm", choices=WIRES,
                   help="the files' encoding: cpm (ETSI TS 103 324 CPM, UPER; default), sdsm (SAE J3224 SDSM as v2i "
                        "writes it), v2i")
    d.add_argument("--json", metavar="PATH", help="write one JSON line a file to PATH ('-': standard output): "
                   "reference position and time, objects (x, y east / north of the reference, metres), or the reason")
    d.set_defaults(func=run)
