"""The CPM against the ETSI conformance vectors (tests/data/cpm_vectors.jsonl: 60 valid CPMs encoded
from the published TS 103 324 V2.1.1 / CDD V2.2.1 modules, with their decoded values) and against
thousands of random valid CPMs shaped like them: every one read right, refused with a reason, or
(its invalid ones) refused; never misread."""

from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from schemas import cpm, enu, its_time
from schemas import standard_wire as sw
from schemas.classes import ObjectClass
from schemas.codec import CodecError
from schemas.messages import UNKNOWN_VELOCITY_VAR, ObjectListHeader

VECTORS = [json.loads(line) for line in (Path(__file__).parents[1] / "data" / "cpm_vectors.jsonl").open()]
TYPES = cpm.CONTAINER_TYPES
OUT_OF_RANGE = (-131072, 131071)


def _asn1(v):
    """asn1tools' value of the vectors' JSON form (CHOICE -> (name, value), BIT STRING -> (bytes, bits))."""
    if isinstance(v, dict):
        if set(v) == {"choice", "value"}:
            return v["choice"], _asn1(v["value"])
        if set(v) == {"bits", "length"}:
            return bytes.fromhex(v["bits"]), v["length"]
        return {k: _asn1(x) for k, x in v.items()}
    return [_asn1(x) for x in v] if isinstance(v, list) else v


def _spec():
    return sw.compiled(cpm.ASN1_FILE)


# ---------------------------------------------------------------- an independent oracle


def _expected_velocity(obj: dict) -> tuple[float, float] | None:
    """(vx, vy) in the message's frame, or None when the velocity is absent or unavailable."""
    if "velocity" not in obj:
        return None
    kind, v = obj["velocity"]
    if kind == "cartesianVelocity":
        x, y = v["xVelocity"]["value"], v["yVelocity"]["value"]
        return None if 16383 in (x, y) else (x / 100, y / 100)
    s, d = v["velocityMagnitude"]["speedValue"], v["velocityDirection"]["value"]
    if s == 16383 or (d >= 3600 and s):
        return None
    a = math.radians((d % 3600) / 10)
    return s / 100 * math.cos(a), s / 100 * math.sin(a)


def _expected_acceleration(obj: dict) -> tuple[float, float]:
    """(ax, ay) in the message's frame; 0 when absent or unavailable."""
    if "acceleration" not in obj:
        return 0.0, 0.0
    kind, a = obj["acceleration"]
    if kind == "cartesianAcceleration":
        x, y = a["xAcceleration"]["value"], a["yAcceleration"]["value"]
        return (0.0 if x == 161 else x / 10), (0.0 if y == 161 else y / 10)
    m, d = a["accelerationMagnitude"]["accelerationMagnitudeValue"], a["accelerationDirection"]["value"]
    if m == 161 or d >= 3600:
        return 0.0, 0.0
    return m / 10 * math.cos(math.radians(d / 10)), m / 10 * math.sin(math.radians(d / 10))


_VEHICLE = {0: "unknown", 5: "car", 6: "bus", 7: "van", 8: "truck", 9: "truck", 10: "truck", 11: "bus", 14: "truck"}
_VRU = {"pedestrian": "pedestrian", "bicyclistAndLightVruVehicle": "cyclist", "motorcyclist": "motorcycle",
        "animal": "unknown"}


def _expected_class(classification: list | None) -> str:
    if not classification:
        return "unknown"
    best = classification[0]
    for e in classification[1:]:
        if (0 if e["confidence"] == 101 else e["confidence"]) > (0 if best["confidence"] == 101 else best["confidence"]):
            best = e
    kind, v = best["objectClass"]
    if kind == "vehicleSubClass":
        return _VEHICLE[v]
    if kind == "vruSubClass":
        return _VRU[v[0]]
    if kind == "groupSubClass" and "clusterProfiles" in v:
        bits = v["clusterProfiles"][0][0] >> 4
        for k, name in enumerate(("pedestrian", "cyclist", "motorcycle", "unknown")):
            if bits & (8 >> k):
                return name
    return "unknown"


def _misreads(reading: cpm.Reading, objects: list[dict]) -> list[str]:
    """Fields v2i uses that the reading got wrong (empty: read right)."""
    kept = [o for o in objects if o["position"]["xCoordinate"]["value"] not in OUT_OF_RANGE
            and o["position"]["yCoordinate"]["value"] not in OUT_OF_RANGE]
    c = reading.columns
    if len(c["id"]) != len(kept):
        return [f"{len(c['id'])} objects read of {len(kept)}"]
    bad = []
    for i, o in enumerate(kept):
        p = o["position"]
        want = {"id": o.get("objectId", i), "x": p["xCoordinate"]["value"] / 100, "y": p["yCoordinate"]["value"] / 100,
                "z": p["zCoordinate"]["value"] / 100 if "zCoordinate" in p else 0.0,
                "age_s": o.get("objectAge", 0) / 1000, "confidence": o.get("objectPerceptionQuality", 15) / 15}
        for k in ("length", "width", "height"):
            key = {"length": "objectDimensionX", "width": "objectDimensionY", "height": "objectDimensionZ"}[k]
            if key in o and o[key]["value"] != 256:
                want[k] = o[key]["value"] / 10
        if "angles" in o and o["angles"]["zAngle"]["value"] < 3600:
            want["yaw"] = math.radians(o["angles"]["zAngle"]["value"] / 10)
        rate = o.get("zAngularVelocity", {"value": 256})["value"]
        want["yaw_rate"] = 0.0 if rate == 256 else math.radians(rate)
        for k, w in want.items():
            got = c[k][i]
            err = abs((got - w + math.pi) % (2 * math.pi) - math.pi) if k == "yaw" else abs(got - w)
            if err > 1e-6:
                bad.append(f"object {i} {k} {got} != {w}")
        a = _expected_acceleration(o)
        if abs(c["ax"][i] - a[0]) > 1e-6 or abs(c["ay"][i] - a[1]) > 1e-6:
            bad.append(f"object {i} acceleration {c['ax'][i], c['ay'][i]} != {a}")
        v = _expected_velocity(o)
        if v is None and c["cov_vxx"][i] < UNKNOWN_VELOCITY_VAR:
            bad.append(f"object {i} velocity read where none is available")
        if v is not None and (abs(c["vx"][i] - v[0]) > 1e-6 or abs(c["vy"][i] - v[1]) > 1e-6):
            bad.append(f"object {i} velocity {c['vx'][i], c['vy'][i]} != {v}")
        if ObjectClass(int(c["cls"][i])).name.lower() != _expected_class(o.get("classification")):
            bad.append(f"object {i} class {c['cls'][i]}")
        if reading.delta_ms[i] != o["measurementDeltaTime"]:
            bad.append(f"object {i} delta")
    return bad


# ---------------------------------------------------------------- the 60 vectors


@pytest.mark.parametrize("vector", VECTORS, ids=[v["name"] for v in VECTORS])
def test_vector_decodes_to_its_values_and_is_read_right(vector: dict) -> None:
    data = bytes.fromhex(vector["uper_hex"])
    spec = _spec()
    msg = spec.decode("CollectivePerceptionMessage", data)
    assert spec.encode("CollectivePerceptionMessage", msg) == data  # the whole message, byte for byte
    for wrapped, expected in zip(msg["payload"]["cpmContainers"], vector["containers"]):
        assert spec.decode(TYPES[wrapped["containerId"]], wrapped["containerData"]) == _asn1(expected["value"])
    reading = cpm.read(data)
    objects = [o for c in vector["containers"] if c["containerId"] == 5 for o in _asn1(c["value"])["perceivedObjects"]]
    assert _misreads(reading, objects) == []
    management = vector["message"]["payload"]["managementContainer"]
    assert reading.reference_time_ms == management["referenceTime"]
    assert reading.station_id == vector["message"]["header"]["stationId"]


def test_all_vectors_read() -> None:
    readings = [cpm.read(bytes.fromhex(v["uper_hex"])) for v in VECTORS]
    origins = Counter(r.originator for r in readings)
    assert len(readings) == 60 and origins["vehicle"] == 24 and origins["rsu"] == 36


# ---------------------------------------------------------------- meaning: position and time


def _header(t_ns: int = 1_767_225_600_123_456_789) -> ObjectListHeader:
    return ObjectListHeader(rsu_id="rsu-a", seq=7, capture_time_ns=t_ns, publish_time_ns=t_ns + 90_000_000,
                            prediction_ns=0)


def test_reference_position_is_the_site_origin_and_a_point_1_km_away_lands_right() -> None:
    site = (48.137154, 11.576124)
    cols = sw.empty_columns(1)
    cols.update(id=np.array([3.0]), x=np.array([1000.0]), y=np.array([-250.0]))
    data = cpm.encode(_header(), cols, origin=site)
    reading = cpm.read(data)
    assert (reading.lat_deg, reading.lon_deg) == pytest.approx(site, abs=1e-7)
    # a third party places the object by the reference position: WGS84 of (1000 E, 250 S) of the origin
    lat, lon = enu.enu_to_geo(reading.columns["x"][0], reading.columns["y"][0], (reading.lat_deg, reading.lon_deg))
    assert enu.geo_to_enu(lat, lon, site) == pytest.approx((1000.0, -250.0), abs=0.01)
    # an OBU of the same site gets the map point back; one whose site origin lies 1 km west sees it at the same
    # WGS84 point, in its own plane: ~1 km further east (the planes' north axes differ by ~0.007 degrees here)
    _, out = cpm.decode(data, origin=site)
    assert (out["x"][0], out["y"][0]) == pytest.approx((1000.0, -250.0), abs=0.01)
    west = enu.enu_to_geo(-1000.0, 0.0, site)
    _, out = cpm.decode(data, origin=west)
    assert (out["x"][0], out["y"][0]) == pytest.approx(enu.geo_to_enu(lat, lon, west), abs=0.01)
    assert (out["x"][0], out["y"][0]) == pytest.approx((2000.0, -250.0), abs=0.5)


def test_enu_agrees_with_lanelet2_local_cartesian() -> None:
    lanelet2 = pytest.importorskip("lanelet2")
    from lanelet2.projection import LocalCartesianProjector

    origin = (48.137154, 11.576124)
    lat, lon = enu.enu_to_geo(1000.0, 700.0, origin)
    p = LocalCartesianProjector(lanelet2.io.Origin(*origin)).forward(lanelet2.core.GPSPoint(lat, lon, 0.0))
    assert (p.x, p.y) == pytest.approx(enu.geo_to_enu(lat, lon, origin), abs=1e-3)


def test_reference_time_is_tai_since_2004_with_the_leap_seconds() -> None:
    # the CDD's example: 2007-01-01T00:00:00.000 UTC is 94 694 401 000 (the 2005-12-31 leap second)
    t2007 = 1_167_609_600 * 10**9
    assert its_time.its_ms(t2007) == 94_694_401_000
    t2026 = 1_767_225_600 * 10**9  # 2026-01-01: 5 leap seconds since 2004
    assert its_time.its_ms(t2026) == (t2026 // 10**6 - its_time.ITS_EPOCH_UNIX_MS) + 5000
    for t in (t2007, t2026, 1_136_073_599_500 * 10**6, 1_136_073_600_000 * 10**6):  # around the 2005 leap second
        assert its_time.unix_ns(its_time.its_ms(t)) == t
    header, _ = cpm.decode(cpm.encode(_header(t2026), sw.empty_columns(1)))
    assert header.publish_time_ns == t2026 + 90_000_000 and header.capture_time_ns == t2026
    # no object, no measurement time: the list is taken as measured at its reference (publish) time
    header, _ = cpm.decode(cpm.encode(_header(t2026), sw.empty_columns(0)))
    assert header.capture_time_ns == header.publish_time_ns == t2026 + 90_000_000


def test_vehicle_originated_cpm_is_read_in_its_frame_and_placed_or_refused() -> None:
    spec = _spec()
    data = cpm.encode(_header(), {**sw.empty_columns(1), "x": np.array([10.0]), "y": np.array([0.0]),
                                  "vx": np.array([2.0]), "cov_vxx": np.array([0.01]), "cov_vyy": np.array([0.01])})
    msg = spec.decode("CollectivePerceptionMessage", data)
    vehicle = spec.encode("OriginatingVehicleContainer", {"orientationAngle": {"value": 900, "confidence": 10}})
    msg["payload"]["cpmContainers"][0] = {"containerId": 1, "containerData": vehicle}  # heading east
    reading = cpm.read(spec.encode("CollectivePerceptionMessage", msg))
    assert reading.originator == "vehicle" and reading.columns["x"][0] == pytest.approx(10.0)
    # x along the heading (east = 90 degrees from north): 10 m ahead is 10 m east
    _, out = cpm.decode(spec.encode("CollectivePerceptionMessage", msg))
    assert (out["x"][0], out["y"][0], out["vx"][0]) == pytest.approx((10.0, 0.0, 2.0), abs=1e-6)
    msg["payload"]["cpmContainers"][0]["containerData"] = spec.encode(
        "OriginatingVehicleContainer", {"orientationAngle": {"value": 0, "confidence": 10}})  # heading north
    _, out = cpm.decode(spec.encode("CollectivePerceptionMessage", msg))
    assert (out["x"][0], out["y"][0], out["vx"][0], out["vy"][0]) == pytest.approx((0.0, 10.0, 0.0, 2.0), abs=1e-6)
    msg["payload"]["cpmContainers"][0]["containerData"] = spec.encode(
        "OriginatingVehicleContainer", {"orientationAngle": {"value": 3601, "confidence": 127}})
    with pytest.raises(CodecError, match="orientation unavailable"):
        cpm.decode(spec.encode("CollectivePerceptionMessage", msg))


def test_the_container_list_is_read_with_and_without_its_size_extension_bit() -> None:
    """X.691: sent with the bit (asn1tools, the published modules); read both (asn1c stacks drop it)."""
    spec = _spec()
    data = cpm.encode(_header(), {**sw.empty_columns(2), "id": np.array([1.0, 2.0]), "x": np.array([5.0, -7.0])})
    msg = spec.decode("CollectivePerceptionMessage", data)
    other = spec.encode("CollectivePerceptionMessageRootSize", msg)
    assert other != data
    a, b = cpm.read(data), cpm.read(other)
    assert not a.root_size and b.root_size
    np.testing.assert_array_equal(a.columns["x"], b.columns["x"])


# ---------------------------------------------------------------- random valid CPMs


def _object_templates() -> list[dict]:
    return [o for v in VECTORS for c in v["containers"] if c["containerId"] == 5
            for o in _asn1(c["value"])["perceivedObjects"]]


def _class_entry(rng: np.random.Generator) -> dict:
    kind = rng.integers(0, 4)
    if kind == 0:
        value: object = ("vehicleSubClass", int(rng.choice([0, 5, 6, 7, 8, 9, 10, 11, 14])))
    elif kind == 1:
        value = ("vruSubClass", (str(rng.choice(list(_VRU))), int(rng.integers(0, 16))))
    elif kind == 2:
        value = ("groupSubClass", {"clusterCardinalitySize": int(rng.integers(0, 256)),
                                   "clusterProfiles": (bytes([int(rng.integers(0, 16)) << 4]), 4)})
    else:
        value = ("otherSubClass", int(rng.integers(0, 256)))
    return {"objectClass": value, "confidence": int(rng.integers(1, 102))}


def _random_object(rng: np.random.Generator, template: dict, delta: int) -> dict:
    o = {**template}
    o["measurementDeltaTime"] = delta
    if rng.random() < 0.95:
        o["objectId"] = int(rng.integers(0, 65536))
    else:
        o.pop("objectId", None)
    pos = {}
    for axis in ("xCoordinate", "yCoordinate") + (("zCoordinate",) if rng.random() < 0.5 else ()):
        value = int(rng.choice(OUT_OF_RANGE)) if rng.random() < 0.02 else int(rng.integers(-131071, 131071))
        pos[axis] = {"value": value, "confidence": int(rng.integers(1, 4097))}
    o["position"] = pos
    r = rng.random()
    if r < 0.4:
        o["velocity"] = ("cartesianVelocity", {k: {"value": int(rng.choice([rng.integers(-16383, 16384), 16383],
                                                                              p=[0.97, 0.03])),
                                                   "confidence": int(rng.integers(1, 128))}
                                               for k in ("xVelocity", "yVelocity")})
    elif r < 0.8:
        o["velocity"] = ("polarVelocity", {
            "velocityMagnitude": {"speedValue": int(rng.choice([rng.integers(0, 16384), 0, 16383], p=[0.9, 0.05, 0.05])),
                                  "speedConfidence": int(rng.integers(1, 128))},
            "velocityDirection": {"value": int(rng.integers(0, 3602)), "confidence": int(rng.integers(1, 128))}})
    else:
        o.pop("velocity", None)
    if rng.random() < 0.5:
        o["angles"] = {"zAngle": {"value": int(rng.integers(0, 3602)), "confidence": int(rng.integers(1, 128))}}
    if rng.random() < 0.5:
        o["classification"] = [_class_entry(rng) for _ in range(int(rng.integers(1, 4)))]
    return o


def _random_cpm(rng: np.random.Generator, templates: list[dict], spec) -> tuple[bytes, dict, str | None]:
    """(bytes, the value encoded, the expected refusal: None, 'unplaceable' or 'invalid')."""
    n = int(rng.integers(0, 9))
    same_time = rng.random() < 0.5
    base = int(rng.integers(-2048, 2048))
    objects = [_random_object(rng, templates[int(rng.integers(len(templates)))],
                              base if same_time else int(rng.integers(-2048, 2048))) for _ in range(n)]
    expected = None
    if objects and rng.random() < 0.02:  # a vehicleSubClass the standard does not allow
        objects[0]["classification"] = [{"objectClass": ("vehicleSubClass", int(rng.choice([1, 2, 3, 4, 12, 13]))),
                                         "confidence": 50}]
        expected = "invalid"
    containers = [{"containerId": 5, "containerData": spec.encode(
        "PerceivedObjectContainer", {"numberOfPerceivedObjects": n, "perceivedObjects": objects})}]
    r = rng.random()
    vehicle = r < 0.4
    if vehicle:
        angle = int(rng.choice([rng.integers(0, 3600), 3601], p=[0.95, 0.05]))
        containers.append({"containerId": 1, "containerData": spec.encode(
            "OriginatingVehicleContainer", {"orientationAngle": {"value": angle, "confidence": 127}})})
        expected = expected or ("unplaceable" if angle >= 3600 else None)
    elif r < 0.9:
        containers.append({"containerId": 2, "containerData": spec.encode(
            "OriginatingRsuContainer", {"mapReference": ("intersection", {"id": int(rng.integers(0, 65536))})})})
    if rng.random() < 0.2:  # a container v2i does not know: skipped
        containers.append({"containerId": int(rng.integers(6, 17)), "containerData": rng.bytes(int(rng.integers(1, 9)))})
    order = rng.permutation(len(containers))
    lat = int(rng.choice([rng.integers(-800_000_000, 800_000_000), 900_000_001], p=[0.97, 0.03]))
    if lat == 900_000_001:
        expected = expected or "unplaceable"
    value = {"header": {"protocolVersion": 2, "messageId": 14, "stationId": int(rng.integers(0, 2**32))},
             "payload": {"managementContainer": {
                 "referenceTime": int(rng.integers(0, 2**40)),
                 "referencePosition": {"latitude": lat, "longitude": int(rng.integers(-1_800_000_000, 1_800_000_000)),
                                       "positionConfidenceEllipse": {"semiMajorConfidence": 4095,
                                                                     "semiMinorConfidence": 4095,
                                                                     "semiMajorOrientation": 3601},
                                       "altitude": {"altitudeValue": 800001, "altitudeConfidence": "unavailable"}}},
                 "cpmContainers": [containers[k] for k in order]}}
    heading = angle / 10 if vehicle else None
    return (spec.encode("CollectivePerceptionMessage", value),
            {"objects": objects, "heading": heading, "same_time": same_time}, expected)


def _misplaced(reading: cpm.Reading, placed: dict, value: dict) -> str:
    """Placed at the reference position (the receiver's origin here): an RSU's objects where they were
    read, a vehicle's turned from its heading (x along it) to east / north; '' when right."""
    if not value["same_time"] or not len(placed["x"]):
        return ""
    x, y, vx, vy = (reading.columns[k] for k in ("x", "y", "vx", "vy"))
    if value["heading"] is not None:  # x axis at heading h clockwise from north: east = x sin h - y cos h ...
        h = math.radians(value["heading"])
        x, y = x * math.sin(h) - y * math.cos(h), x * math.cos(h) + y * math.sin(h)
        vx, vy = vx * math.sin(h) - vy * math.cos(h), vx * math.cos(h) + vy * math.sin(h)
    for k, want, tol in (("x", x, 1e-6), ("y", y, 1e-6), ("vx", vx, 1e-9), ("vy", vy, 1e-9)):
        if np.abs(placed[k] - want).max() > tol:
            return f"placed {k} {placed[k]} != {want}"
    return ""


def test_random_valid_cpms_are_never_misread() -> None:
    rng = np.random.default_rng(2026)
    spec, templates = _spec(), _object_templates()
    n, tally, misread = 3000, Counter(), []
    for _ in range(n):
        data, value, expected = _random_cpm(rng, templates, spec)
        try:
            reading = cpm.read(data)
        except CodecError as exc:
            tally[f"refused read: {exc.reason}"] += 1
            if expected != "invalid":
                misread.append(f"refused a valid CPM: {exc}")
            continue
        if expected == "invalid":
            misread.append("read an invalid CPM")
            continue
        wrong = _misreads(reading, value["objects"])
        if wrong:
            misread.append("; ".join(wrong[:3]))
            continue
        try:
            origin = (0.0, 0.0) if reading.lat_deg is None else (reading.lat_deg, reading.lon_deg)
            _, placed = cpm.decode(data, origin=origin)
        except CodecError as exc:
            tally["refused place: " + str(exc).split(":", 1)[-1].strip()] += 1
            if expected != "unplaceable":
                misread.append(f"refused a placeable CPM: {exc}")
            continue
        if expected == "unplaceable":
            misread.append("placed an unplaceable CPM")
            continue
        wrong = _misplaced(reading, placed, value)
        if wrong:
            misread.append(wrong)
            continue
        tally["read"] += 1
        tally.update(f"skipped {k}" for k, c in reading.skipped.items() for _ in range(c))
    print(f"\nrandom CPMs: {n}, misread {len(misread)}:", json.dumps(dict(sorted(tally.items())), indent=1))
    assert misread == []
    assert tally["read"] > n * 0.8
