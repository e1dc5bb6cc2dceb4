"""``v2i wire decode``: one JSON line a file, read by v2i's codecs, or the reason it was refused."""

from __future__ import annotations

import json
from pathlib import Path


from schemas import cpm, list_wire
from schemas import standard_wire as sw
from schemas.messages import ObjectList, ObjectListHeader
from v2i.wire_cli import configure_parser, decode_file

VECTORS = [json.loads(line) for line in (Path(__file__).parents[1] / "data" / "cpm_vectors.jsonl").open()]
T0 = 1_767_225_600_000_000_000


def _run(argv: list[str], capsys) -> tuple[int, list[dict]]:
    import argparse

    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="command")
    configure_parser(sub.add_parser("wire"))
    args = p.parse_args(["wire", *argv])
    rc = args.func(args)
    return rc, [json.loads(line) for line in capsys.readouterr().out.splitlines()]


def test_vectors_decode_with_their_positions(tmp_path: Path, capsys) -> None:
    files = []
    for v in VECTORS[:12]:
        (tmp_path / v["name"]).write_bytes(bytes.fromhex(v["uper_hex"]))
        files.append(str(tmp_path / v["name"]))
    rc, rows = _run(["decode", *files, "--wire", "cpm", "--json", "-"], capsys)
    assert rc == 0 and [r["file"] for r in rows] == files and all(r["ok"] for r in rows)
    for v, row in zip(VECTORS, rows):
        objects = [o for c in v["containers"] if c["containerId"] == 5 for o in c["value"]["perceivedObjects"]
                   if o["position"]["xCoordinate"]["value"] not in (-131072, 131071)
                   and o["position"]["yCoordinate"]["value"] not in (-131072, 131071)]
        assert [(o["x_m"], o["y_m"]) for o in row["objects"]] == [
            (o["position"]["xCoordinate"]["value"] / 100, o["position"]["yCoordinate"]["value"] / 100) for o in objects]
        assert row["reference"]["time_tai_ms"] == v["message"]["payload"]["managementContainer"]["referenceTime"]
        beyond = [o for c in v["containers"] if c["containerId"] == 5 for o in c["value"]["perceivedObjects"]
                  if o not in objects]
        assert [(o["x_m"], o["y_m"]) for o in row["objects_out_of_range"]] == [
            (o["position"]["xCoordinate"]["value"] / 100, o["position"]["yCoordinate"]["value"] / 100) for o in beyond]


def test_each_wire_and_a_refusal(tmp_path: Path) -> None:
    header = ObjectListHeader(rsu_id="rsu-a", seq=3, capture_time_ns=T0, publish_time_ns=T0 + 90_000_000)
    msg = ObjectList(header=header, objects=[{"id": 4, "cls": 1, "x": 12.34, "y": -5.67, "vx": 3.0, "cov_vxx": 0.04,
                                                "cov_vyy": 0.04, "length": 4.5, "width": 1.8}])
    for wire in ("cpm", "sdsm", "v2i"):
        (tmp_path / wire).write_bytes(list_wire.encode_list(msg, wire, origin=(48.1, 11.6)))
        row = decode_file(tmp_path / wire, wire)
        assert row["ok"] and row["objects"][0]["class"] == "car", wire
        assert abs(row["objects"][0]["x_m"] - 12.34) <= 0.05 and abs(row["objects"][0]["y_m"] + 5.67) <= 0.05, wire
    assert decode_file(tmp_path / "cpm", "cpm")["reference"]["lat_deg"] == 48.1
    (tmp_path / "bad").write_bytes(b"\x01\x02")
    row = decode_file(tmp_path / "bad", "cpm")
    assert not row["ok"] and row["reason"].startswith("malformed")
    assert not decode_file(tmp_path / "missing", "cpm")["ok"]
    data = cpm.encode(header, sw.empty_columns(0))
    assert decode_file(_write(tmp_path / "empty", data), "cpm")["objects"] == []


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path
