"""RSU object lists as collective perception messages (ETSI CPM, release 2) in UPER.

``encode(header, objects) -> bytes`` and ``decode(data, rsu_id=None) -> (header, columns)``
over the ASN.1 in ``asn1/V2I-CPM.asn`` (see ``asn1/README.md``: written for this project after
TS 103 324 / TS 102 894-2; not the published ETSI module). ``objects``: an ``ObjectArray``, wire
objects or object columns; ``columns``: object columns (``schemas.standard_wire``).

Mapping (v2i -> CPM; decode is the inverse, at the CPM's resolution):

==========================  =================================================  ======================
v2i                         CPM                                                quantisation / range
==========================  =================================================  ======================
rsu_id                      header.stationId (``station_id``, default crc32)   decode: the key's id
seq                         managementContainer.v2iSequence (extension)        absent: referenceTime
capture_time_ns             managementContainer.referenceTime                  1 ms (since 2004)
publish_time_ns             managementContainer.v2iPublishDelta (extension)    1 ms after capture
prediction_ns               perceivedObject.measurementDeltaTime               1 ms, 0..2047 ms
frame ``map`` origin        managementContainer.referencePosition              site origin (lat, lon)
id                          objectId                                           modulo 65536
x, y, z                     position.{x,y,z}Coordinate.value                   0.01 m, +-1310.7 m
cov_xx, cov_yy              position.{x,y}Coordinate.confidence = 1.96 sigma   0.01 m (<= 40.94 m)
cov_xy, cov_vxy             lowerTriangularCorrelationMatrices (rho)           1 %
vx, vy                      velocity.cartesianVelocity.{x,y}Velocity.value     0.01 m/s, +-163.8 m/s
cov_vxx, cov_vyy            {x,y}Velocity.confidence = 1.96 sigma              0.01 m/s (<= 1.25 m/s)
ax, ay                      acceleration.cartesianAcceleration                 0.1 m/s^2, +-16 m/s^2
yaw                         angles.zAngle (counter-clockwise from x = east)    0.1 degree
yaw_rate                    zAngularVelocity                                   1 degree/s, +-254
length, width, height       objectDimensionX, Y, Z                             0.1 m, 0.1..25.6 m
age_s                       objectAge                                          1 ms, <= 2.047 s
confidence                  objectPerceptionQuality                            1/15
cls                         classification (vehicle / VRU sub-class)           ``CLASS_TO_CPM``
==========================  =================================================  ======================

A velocity variance of ``UNKNOWN_VELOCITY_VAR`` (not measured) omits the velocity; a speed
confidence beyond 1.25 m/s is sent as ``outOfRange`` and read back as ``SPEED_OUT_OF_RANGE_SIGMA``.
Acceleration, z, yaw rate and correlations are omitted when zero. More than 255 objects, a
position beyond +-1310.7 m from the site origin, or a non-finite value: ``InvalidMessage``.
"""

from __future__ import annotations

import zlib
from typing import Any

import numpy as np

from schemas import standard_wire as sw
from schemas.classes import ObjectClass
from schemas.codec import InvalidMessage, WrongMessageType
from schemas.messages import UNKNOWN_VELOCITY_VAR, ObjectListHeader

ASN1_FILE = "V2I-CPM.asn"
MESSAGE_ID = 14
PROTOCOL_VERSION = 2
RSU_CONTAINER, OBJECT_CONTAINER = 2, 5
MAX_CPM_OBJECTS = MAX_OBJECTS = 255
POSITION_LIMIT = 131070  # 0.01 m codes; 131071 / -131072 mean out of range
POSITION_RANGE_M = POSITION_LIMIT * 0.01
SPEED_OUT_OF_RANGE_SIGMA = 2.0  # m/s: what a speed confidence "outOfRange" (> 1.25 m/s at 95 %) is read as
SENSOR = "cpm"
_D = np.pi / 180.0

# v2i class -> ("vehicleSubClass" TrafficParticipantType | "vruSubClass" profile, value)
CLASS_TO_CPM: dict[int, tuple[str, Any]] = {
    ObjectClass.UNKNOWN: ("vehicleSubClass", 0), ObjectClass.CAR: ("vehicleSubClass", 5),
    ObjectClass.VAN: ("vehicleSubClass", 7), ObjectClass.TRUCK: ("vehicleSubClass", 8),
    ObjectClass.BUS: ("vehicleSubClass", 6), ObjectClass.MOTORCYCLE: ("vehicleSubClass", 4),
    ObjectClass.PEDESTRIAN: ("vruSubClass", ("pedestrian", 0)),
    ObjectClass.CYCLIST: ("vruSubClass", ("bicyclistAndLightVruVehicle", 0)),
}
_VEHICLE_TO_V2I = {1: ObjectClass.PEDESTRIAN, 2: ObjectClass.CYCLIST, 3: ObjectClass.MOTORCYCLE,
                   4: ObjectClass.MOTORCYCLE, 5: ObjectClass.CAR, 6: ObjectClass.BUS, 7: ObjectClass.VAN,
                   8: ObjectClass.TRUCK, 9: ObjectClass.TRUCK, 11: ObjectClass.BUS, 12: ObjectClass.CYCLIST}
_VRU_TO_V2I = {"pedestrian": ObjectClass.PEDESTRIAN, "bicyclistAndLightVruVehicle": ObjectClass.CYCLIST,
               "motorcyclist": ObjectClass.MOTORCYCLE}


def station_id(rsu_id: str) -> int:
    """Default ETSI station id of an RSU id: CRC-32 of its name."""
    return zlib.crc32(rsu_id.encode())


def _spec():
    return sw.compiled(ASN1_FILE)


# ---------------------------------------------------------------- encode


def _codes(v: np.ndarray, step: float, lo: int, hi: int) -> list[int]:
    """Integer codes round(v / step) saturated to [lo, hi] (the standard's out-of-range codes)."""
    return np.clip(np.rint(v / step), lo, hi).astype(np.int64).tolist()


def _confidence(var: np.ndarray, step: float, hi: int) -> list[int]:
    """95 % confidence codes: ceil(1.96 sigma / step) in [1, hi] (hi: out of range)."""
    return np.clip(np.ceil(sw.Z95 * np.sqrt(np.maximum(var, 0.0)) / step - 1e-9), 1, hi).astype(np.int64).tolist()


def _rho(cov: np.ndarray, vx: np.ndarray, vy: np.ndarray) -> list[int]:
    """Correlation in percent: rho = cov / sqrt(var_x var_y)."""
    den = np.sqrt(np.maximum(vx, 0.0) * np.maximum(vy, 0.0))
    rho = np.divide(cov, den, out=np.zeros_like(cov), where=den > 0)
    return np.clip(np.rint(100.0 * rho), -100, 100).astype(np.int64).tolist()


def _check(c: dict[str, np.ndarray], n: int) -> None:
    if n > MAX_CPM_OBJECTS:
        raise InvalidMessage(f"objects: {n} objects, a CPM carries at most {MAX_CPM_OBJECTS}", "objects")
    for name, col in c.items():
        if not np.isfinite(col).all():
            raise InvalidMessage(f"objects.{int(np.flatnonzero(~np.isfinite(col))[0])}.{name} is not finite",
                                 f"objects.{name}")
    for name in ("x", "y", "z"):
        bad = np.abs(np.rint(c[name] / 0.01)) > POSITION_LIMIT
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InvalidMessage(f"objects.{i}.{name} = {c[name][i]} is beyond the CPM's +-1310.7 m", f"objects.{i}.{name}")


def _object(c: dict[str, list], i: int, delta_ms: int) -> dict:
    """One PerceivedObject of the per-column code lists ``c``."""
    obj: dict[str, Any] = {
        "objectId": c["id"][i], "measurementDeltaTime": delta_ms,
        "position": {"xCoordinate": {"value": c["x"][i], "confidence": c["cx"][i]},
                     "yCoordinate": {"value": c["y"][i], "confidence": c["cy"][i]}},
        "angles": {"zAngle": {"value": c["yaw"][i], "confidence": 127}},
        "objectDimensionZ": {"value": c["height"][i], "confidence": 102},
        "objectDimensionY": {"value": c["width"][i], "confidence": 102},
        "objectDimensionX": {"value": c["length"][i], "confidence": 102},
        "objectAge": c["age"][i], "objectPerceptionQuality": c["quality"][i],
        "classification": [{"objectClass": CLASS_TO_CPM.get(c["cls"][i], ("vehicleSubClass", 0)), "confidence": 101}],
    }
    if c["z"][i]:
        obj["position"]["zCoordinate"] = {"value": c["z"][i], "confidence": 4096}
    if c["vknown"][i]:
        obj["velocity"] = ("cartesianVelocity", {"xVelocity": {"value": c["vx"][i], "confidence": c["cvx"][i]},
                                                 "yVelocity": {"value": c["vy"][i], "confidence": c["cvy"][i]}})
    if c["ax"][i] or c["ay"][i]:
        obj["acceleration"] = ("cartesianAcceleration", {"xAcceleration": {"value": c["ax"][i], "confidence": 102},
                                                         "yAcceleration": {"value": c["ay"][i], "confidence": 102}})
    if c["yaw_rate"][i]:
        obj["zAngularVelocity"] = {"value": c["yaw_rate"][i], "confidence": "unavailable"}
    matrices = _correlations(c["rho"][i], c["rhov"][i], c["vknown"][i])
    if matrices:
        obj["lowerTriangularCorrelationMatrices"] = matrices
    return obj


def _correlations(rho: int, rho_v: int, velocity: bool) -> list[dict]:
    """Position (x, y) and velocity (vx, vy) correlations as one lower-triangular matrix; [] if all 0."""
    if not rho and not (velocity and rho_v):
        return []
    if not velocity:  # components x, y: one column [rho]
        return [{"componentsIncludedIntheMatrix": (b"\xc0\x00", 13), "matrix": [[rho]]}]
    # components x, y, vx, vy: columns [rho(x,y), rho(x,vx), rho(x,vy)], [rho(y,vx), rho(y,vy)], [rho(vx,vy)]
    return [{"componentsIncludedIntheMatrix": (b"\xd8\x00", 13), "matrix": [[rho, 0, 0], [0, 0], [rho_v]]}]


def _code_columns(c: dict[str, np.ndarray]) -> dict[str, list]:
    """Per-column integer codes (lists) of object columns."""
    vknown = (c["cov_vxx"] < UNKNOWN_VELOCITY_VAR) | (c["cov_vyy"] < UNKNOWN_VELOCITY_VAR)
    # zAngle: counter-clockwise from x in [0, 360) degrees, 0.1 degree
    yaw = np.mod(np.rint(np.mod(c["yaw"], 2 * np.pi) / (0.1 * _D)), 3600)
    return {
        "id": np.mod(c["id"], 65536).astype(np.int64).tolist(), "cls": c["cls"].astype(np.int64).tolist(),
        "x": _codes(c["x"], 0.01, -131072, 131071), "y": _codes(c["y"], 0.01, -131072, 131071),
        "z": _codes(c["z"], 0.01, -131072, 131071),
        "cx": _confidence(c["cov_xx"], 0.01, 4095), "cy": _confidence(c["cov_yy"], 0.01, 4095),
        "rho": _rho(c["cov_xy"], c["cov_xx"], c["cov_yy"]), "rhov": _rho(c["cov_vxy"], c["cov_vxx"], c["cov_vyy"]),
        "vknown": vknown.tolist(), "vx": _codes(c["vx"], 0.01, -16383, 16382), "vy": _codes(c["vy"], 0.01, -16383, 16382),
        "cvx": _confidence(c["cov_vxx"], 0.01, 126), "cvy": _confidence(c["cov_vyy"], 0.01, 126),
        "ax": _codes(c["ax"], 0.1, -160, 160), "ay": _codes(c["ay"], 0.1, -160, 160),
        "yaw": yaw.astype(np.int64).tolist(), "yaw_rate": _codes(c["yaw_rate"], _D, -255, 255),
        "length": _codes(c["length"], 0.1, 1, 256), "width": _codes(c["width"], 0.1, 1, 256),
        "height": _codes(c["height"], 0.1, 1, 256), "age": _codes(c["age_s"], 0.001, 0, 2047),
        "quality": _codes(c["confidence"], 1 / 15, 0, 15),
    }


def encode(header: ObjectListHeader, objects: Any, station: int | None = None,
           origin_e7: tuple[int, int] = sw.SITE_ORIGIN_E7) -> bytes:
    """UPER CPM of an RSU object list (positions in ``map``); ``station``: ETSI station id
    (default ``station_id(header.rsu_id)``). Raises InvalidMessage for what a CPM cannot carry."""
    cols = sw.columns_of(objects)
    n = len(cols["id"])
    _check(cols, n)
    if header.prediction_ns > 2_047_000_000:
        raise InvalidMessage(f"header.prediction_ns {header.prediction_ns} is beyond the CPM's 2047 ms", "header.prediction_ns")
    delta_ms = round(header.prediction_ns / 1e6)
    codes = _code_columns(cols)
    spec = _spec()
    container = {"numberOfPerceivedObjects": n, "perceivedObjects": [_object(codes, i, delta_ms) for i in range(n)]}
    lat, lon = origin_e7
    reference_ms = sw.its_ms(header.capture_time_ns)
    management = {
        "referenceTime": reference_ms,
        "referencePosition": {"latitude": lat, "longitude": lon,
                              "positionConfidenceEllipse": {"semiMajorAxisLength": 4095, "semiMinorAxisLength": 4095,
                                                            "semiMajorAxisOrientation": 3601},
                              "altitude": {"altitudeValue": 800001, "altitudeConfidence": "unavailable"}},
        "v2iSequence": header.seq,
        "v2iPublishDelta": min(max(sw.its_ms(header.publish_time_ns) - reference_ms, 0), 65535),
    }
    wrapped = [{"containerId": RSU_CONTAINER, "containerData": sw.asn1_encode(spec, "OriginatingRsuContainer", {}, "cpm")},
               {"containerId": OBJECT_CONTAINER,
                "containerData": sw.asn1_encode(spec, "PerceivedObjectContainer", container, "cpm")}]
    message = {"header": {"protocolVersion": PROTOCOL_VERSION, "messageId": MESSAGE_ID,
                          "stationId": station_id(header.rsu_id) if station is None else station},
               "payload": {"managementContainer": management, "cpmContainers": wrapped}}
    return sw.asn1_encode(spec, "CollectivePerceptionMessage", message, "cpm")


# ---------------------------------------------------------------- decode


def _cls(classification: list | None) -> int:
    if not classification:
        return int(ObjectClass.UNKNOWN)
    kind, value = classification[0]["objectClass"]
    if kind == "vehicleSubClass":
        return int(_VEHICLE_TO_V2I.get(value, ObjectClass.UNKNOWN))
    if kind == "vruSubClass":
        return int(_VRU_TO_V2I.get(value[0], ObjectClass.UNKNOWN))
    return int(ObjectClass.UNKNOWN)


def _sigma(conf: int, step: float, out_of_range: int, unavailable: int, fallback: float) -> float:
    """sigma of a 95 % confidence code (conf * step / 1.96); ``fallback`` when out of range or unavailable."""
    return fallback if conf >= out_of_range else conf * step / sw.Z95


def _rhos(obj: dict) -> tuple[float, float]:
    """(rho_xy, rho_vxvy) of an object's first correlation matrix (x, y[, vx, vy]); 0 if absent."""
    matrices = obj.get("lowerTriangularCorrelationMatrices") or ()
    for m in matrices:
        bits = int.from_bytes(m["componentsIncludedIntheMatrix"][0], "big") >> 3  # 13 bits, MSB first
        cols = m["matrix"]
        if bits == 0b1100000000000:
            return _cell(cols, 0, 0) / 100.0, 0.0
        if bits == 0b1101100000000:
            return _cell(cols, 0, 0) / 100.0, _cell(cols, 2, 0) / 100.0
    return 0.0, 0.0


def _cell(cols: list[list[int]], j: int, k: int) -> int:
    """Correlation cell (percent) k of column j; 0 when absent or unavailable (101)."""
    return cols[j][k] if j < len(cols) and k < len(cols[j]) and cols[j][k] != 101 else 0


def _fill(cols: dict[str, np.ndarray], i: int, obj: dict, ref_xy: tuple[float, float]) -> None:
    """Row ``i`` of the object columns from one decoded PerceivedObject."""
    pos = obj["position"]
    cols["id"][i] = obj.get("objectId", i)
    cols["x"][i] = ref_xy[0] + pos["xCoordinate"]["value"] * 0.01
    cols["y"][i] = ref_xy[1] + pos["yCoordinate"]["value"] * 0.01
    cols["z"][i] = pos["zCoordinate"]["value"] * 0.01 if "zCoordinate" in pos else 0.0
    sx = _sigma(pos["xCoordinate"]["confidence"], 0.01, 4095, 4096, 100.0)
    sy = _sigma(pos["yCoordinate"]["confidence"], 0.01, 4095, 4096, 100.0)
    rho, rho_v = _rhos(obj)
    cols["cov_xx"][i], cols["cov_yy"][i], cols["cov_xy"][i] = sx * sx, sy * sy, rho * sx * sy
    kind, vel = obj.get("velocity", (None, None))
    if kind == "cartesianVelocity":
        cols["vx"][i], cols["vy"][i] = vel["xVelocity"]["value"] * 0.01, vel["yVelocity"]["value"] * 0.01
        svx = _sigma(vel["xVelocity"]["confidence"], 0.01, 126, 127, SPEED_OUT_OF_RANGE_SIGMA)
        svy = _sigma(vel["yVelocity"]["confidence"], 0.01, 126, 127, SPEED_OUT_OF_RANGE_SIGMA)
        cols["cov_vxx"][i], cols["cov_vyy"][i], cols["cov_vxy"][i] = svx * svx, svy * svy, rho_v * svx * svy
    elif kind == "polarVelocity":  # magnitude and direction (counter-clockwise from x)
        speed, heading = vel["velocityMagnitude"]["speedValue"] * 0.01, vel["velocityDirection"]["value"] * 0.1 * _D
        cols["vx"][i], cols["vy"][i] = speed * np.cos(heading), speed * np.sin(heading)
        s = _sigma(vel["velocityMagnitude"]["speedConfidence"], 0.01, 126, 127, SPEED_OUT_OF_RANGE_SIGMA)
        cols["cov_vxx"][i] = cols["cov_vyy"][i] = s * s
    kind, acc = obj.get("acceleration", (None, None))
    if kind == "cartesianAcceleration":
        ax, ay = acc["xAcceleration"]["value"], acc["yAcceleration"]["value"]
        cols["ax"][i], cols["ay"][i] = (0.0 if ax == 161 else ax * 0.1), (0.0 if ay == 161 else ay * 0.1)
    yaw_code = obj["angles"]["zAngle"]["value"] if "angles" in obj else 3601
    cols["yaw"][i] = 0.0 if yaw_code >= 3600 else ((yaw_code * 0.1 + 180.0) % 360.0 - 180.0) * _D
    rate = obj.get("zAngularVelocity", {"value": 0})["value"]
    cols["yaw_rate"][i] = 0.0 if rate == 256 else rate * _D
    for name, key in (("length", "objectDimensionX"), ("width", "objectDimensionY"), ("height", "objectDimensionZ")):
        if key in obj:
            cols[name][i] = obj[key]["value"] * 0.1
    cols["age_s"][i] = obj.get("objectAge", 0) * 0.001
    cols["confidence"][i] = obj.get("objectPerceptionQuality", 15) / 15.0
    cols["cls"][i] = _cls(obj.get("classification"))


def _objects(containers: list[dict], spec) -> list[dict]:
    """The PerceivedObjects of the (one) perceived object container; [] when there is none."""
    found = [c for c in containers if c["containerId"] == OBJECT_CONTAINER]
    if len(found) > 1:
        raise InvalidMessage(f"cpm has {len(found)} perceived object containers, at most 1 allowed", "cpmContainers")
    if not found:
        return []
    container = sw.asn1_decode(spec, "PerceivedObjectContainer", found[0]["containerData"], "cpm perceived objects")
    objects = container["perceivedObjects"]
    if container["numberOfPerceivedObjects"] != len(objects):
        raise InvalidMessage(f"numberOfPerceivedObjects {container['numberOfPerceivedObjects']} but "
                             f"{len(objects)} objects", "numberOfPerceivedObjects")
    return objects


@sw.guarded("cpm")
def decode(data: bytes, rsu_id: str | None = None, max_bytes: int = sw.MAX_STANDARD_BYTES,
           origin_e7: tuple[int, int] = sw.SITE_ORIGIN_E7) -> tuple[ObjectListHeader, dict[str, np.ndarray]]:
    """(header, object columns) of a UPER CPM. ``rsu_id``: the id the message came under (its key);
    None names the RSU ``station<stationId>``. Every failure is a CodecError."""
    spec = _spec()
    msg = sw.asn1_decode(spec, "CollectivePerceptionMessage", sw.check_size(data, max_bytes, "cpm"), "cpm")
    head, payload = msg["header"], msg["payload"]
    if head["messageId"] != MESSAGE_ID or head["protocolVersion"] != PROTOCOL_VERSION:
        raise WrongMessageType(f"ITS message id {head['messageId']} version {head['protocolVersion']} received "
                               f"where a CPM (id {MESSAGE_ID}, version {PROTOCOL_VERSION}) was expected")
    management = payload["managementContainer"]
    objects = _objects(payload["cpmContainers"], spec)
    deltas = {o["measurementDeltaTime"] for o in objects}
    if len(deltas) > 1:
        raise InvalidMessage(f"cpm objects measured at {len(deltas)} different times; a v2i list has one", "objects")
    delta_ms = deltas.pop() if deltas else 0
    reference_ms = management["referenceTime"]
    capture_ms = reference_ms + min(delta_ms, 0)  # a measurement before the reference time: captured then
    capture_ns = (capture_ms + sw.ITS_EPOCH_MS) * 1_000_000
    publish_ns = (reference_ms + management.get("v2iPublishDelta", 0) + sw.ITS_EPOCH_MS) * 1_000_000
    position = management["referencePosition"]
    if position["latitude"] > 900_000_000 or position["longitude"] > 1_800_000_000:
        raise InvalidMessage("cpm reference position unavailable", "referencePosition")
    ref_xy = sw.geo_e7_to_map(position["latitude"], position["longitude"], origin_e7)
    cols = sw.empty_columns(len(objects))
    for i, obj in enumerate(objects):
        _fill(cols, i, obj, ref_xy)
    hdr = sw.header(rsu_id or f"station{head['stationId']}", management.get("v2iSequence", reference_ms),
                    capture_ns, max(publish_ns, capture_ns), max(delta_ms, 0) * 1_000_000, SENSOR)
    return hdr, cols
