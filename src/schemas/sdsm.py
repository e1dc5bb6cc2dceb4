"""RSU object lists as SAE J3224 sensor data sharing messages (SDSM) in UPER.

``encode(header, objects) -> bytes`` and ``decode(data, rsu_id=None) -> (header, columns)``
over ``asn1/V2I-SDSM.asn`` (see ``asn1/README.md``: written for this project after J3224 /
J2735; not SAE's module). ``objects`` and ``columns`` as in ``schemas.cpm``.

Mapping (v2i -> SDSM; decode is the inverse at the SDSM's resolution):

==========================  ==============================================  =========================
v2i                         SDSM                                            quantisation / range
==========================  ==============================================  =========================
rsu_id                      sourceID (4 bytes: ``cpm.station_id``)          decode: the key's id
seq                         msgCnt (seq mod 128) + v2iSequence (extension)  absent: the capture ms
capture_time_ns             sDSMTimeStamp (UTC date, hour, minute, ms)      1 ms
publish_time_ns             v2iPublishDelta (extension)                     1 ms after capture
prediction_ns               measurementTime                                 1 ms, <= 1500 ms
frame ``map`` origin        refPos                                          site origin (lat, lon)
id                          objectID                                        modulo 65536
x, y, z                     pos.offsetX, offsetY, offsetZ                   0.1 m, +-3276.7 m
cov_xx, cov_yy (cov_xy)     posConfidence.pos: 95 % bound, 15 levels        isotropic, cov_xy lost
vx, vy                      speed (magnitude) along heading                 0.02 m/s; direction: heading
cov_vxx, cov_vyy            speedConfidence: 95 % bound, 7 levels           isotropic, cov_vxy lost
yaw                         heading: the velocity's direction when moving   0.0125 degree
                            (>= ``MOVING_MPS``), else the yaw; clockwise
                            from north
ax, ay, yaw_rate            accel4way long / lat (along heading), yaw       0.01 m/s^2, 0.01 degree/s
length, width, height       detVeh size (0.01 m) + height (0.05 m);         VRU: a radius (0.1 m);
                            detVRU radius; detObst size (0.1 m)             height then 1.5 m
confidence                  objTypeCfd                                      1 %
cls                         objType + vehicleClass / VRU basicType          ``CLASS_TO_SDSM``
age_s                       (none)                                          decoded as 0
==========================  ==============================================  =========================

An SDSM carries 1..255 objects: an empty list has no SDSM (``encode`` raises ``EmptyList``;
``schemas.list_wire`` publishes nothing then).
"""

from __future__ import annotations

import datetime as dt
from typing import Any

import numpy as np

from schemas import standard_wire as sw
from schemas.classes import ObjectClass
from schemas.codec import InvalidMessage
from schemas.cpm import station_id
from schemas.messages import UNKNOWN_VELOCITY_VAR, ObjectListHeader

ASN1_FILE = "V2I-SDSM.asn"
MAX_OBJECTS = 255
POSITION_RANGE_M = 3276.7
MOVING_MPS = 0.5
SENSOR = "sdsm"
_D = np.pi / 180.0
# 95 % bounds of PositionConfidence a500m..a1cm and SpeedConfidence prec100ms..prec0-01ms (index 1..)
POSITION_LEVELS_M = (500.0, 200.0, 100.0, 50.0, 20.0, 10.0, 5.0, 2.0, 1.0, 0.5, 0.2, 0.1, 0.05, 0.02, 0.01)
POSITION_ENUM = ("a500m", "a200m", "a100m", "a50m", "a20m", "a10m", "a5m", "a2m", "a1m", "a50cm", "a20cm", "a10cm",
                 "a5cm", "a2cm", "a1cm")
SPEED_LEVELS_MPS = (100.0, 10.0, 5.0, 1.0, 0.1, 0.05, 0.01)
SPEED_ENUM = ("prec100ms", "prec10ms", "prec5ms", "prec1ms", "prec0-1ms", "prec0-05ms", "prec0-01ms")
# v2i class -> (objType, J2735 BasicVehicleClass or PersonalDeviceUserType)
CLASS_TO_SDSM: dict[int, tuple[str, int]] = {
    ObjectClass.UNKNOWN: ("unknown", 0), ObjectClass.CAR: ("vehicle", 10), ObjectClass.VAN: ("vehicle", 20),
    ObjectClass.TRUCK: ("vehicle", 25), ObjectClass.BUS: ("vehicle", 50), ObjectClass.MOTORCYCLE: ("vehicle", 40),
    ObjectClass.PEDESTRIAN: ("vru", 1), ObjectClass.CYCLIST: ("vru", 2),
}
_FROM_SDSM = {v: int(k) for k, v in CLASS_TO_SDSM.items()}


class EmptyList(InvalidMessage):
    """An SDSM carries at least one object."""


def _spec():
    return sw.compiled(ASN1_FILE)


def _level(bound: float, levels: tuple[float, ...], names: tuple[str, ...]) -> str:
    """The finest level whose 95 % bound still covers ``bound`` (the coarsest if none)."""
    fits = [name for level, name in zip(levels, names) if level >= bound]
    return fits[-1] if fits else names[0]


def _time(capture_ns: int) -> dict:
    """DDateTime (UTC, ms within the minute) of a Unix time in ns."""
    ms = (int(capture_ns) + 500_000) // 1_000_000
    t = dt.datetime.fromtimestamp(ms // 1000, dt.UTC)
    return {"year": t.year, "month": t.month, "day": t.day, "hour": t.hour, "minute": t.minute,
            "second": t.second * 1000 + ms % 1000, "offset": 0}


def _unix_ms(stamp: dict) -> int:
    """Unix ms of a complete DDateTime (UTC); InvalidMessage when a part is missing or impossible."""
    parts = ("year", "month", "day", "hour", "minute", "second")
    if any(p not in stamp for p in parts) or stamp["second"] >= 60_000:
        raise InvalidMessage("sdsm time stamp incomplete or out of range", "sDSMTimeStamp")
    try:
        t = dt.datetime(stamp["year"], stamp["month"], stamp["day"], stamp["hour"], stamp["minute"], tzinfo=dt.UTC)
    except ValueError as exc:
        raise InvalidMessage(f"sdsm time stamp: {exc}", "sDSMTimeStamp") from None
    return int(t.timestamp()) * 1000 + stamp["second"] - stamp.get("offset", 0) * 60_000


# ---------------------------------------------------------------- encode


def _heading(c: dict[str, np.ndarray], i: int, moving: bool) -> float:
    """Direction (rad, counter-clockwise from east) the SDSM heading carries: the velocity's when moving."""
    return float(np.arctan2(c["vy"][i], c["vx"][i])) if moving else float(c["yaw"][i])


def _detail(c: dict[str, np.ndarray], i: int, kind: str, sub: int) -> tuple[str, dict]:
    if kind == "vehicle":
        return "detVeh", {"size": {"width": _clip(c["width"][i] / 0.01, 0, 1023),
                                   "length": _clip(c["length"][i] / 0.01, 0, 4095)},
                          "height": _clip(c["height"][i] / 0.05, 0, 127), "vehicleClass": sub}
    if kind == "vru":
        return "detVRU", {"basicType": sub,
                          "radius": _clip(max(c["length"][i], c["width"][i]) / 2 / 0.1, 0, 200)}
    return "detObst", {"obstSize": {"width": _clip(c["width"][i] / 0.1, 0, 1023),
                                    "length": _clip(c["length"][i] / 0.1, 0, 1023),
                                    "height": _clip(c["height"][i] / 0.1, 0, 1023)}}


def _clip(code: float, lo: int, hi: int) -> int:
    """round(code) saturated to [lo, hi]."""
    return min(max(round(float(code)), lo), hi)


def _object(c: dict[str, np.ndarray], i: int, delta_ms: int) -> dict:
    """One DetectedObjectData of row ``i`` of the object columns."""
    known = c["cov_vxx"][i] < UNKNOWN_VELOCITY_VAR or c["cov_vyy"][i] < UNKNOWN_VELOCITY_VAR
    speed = float(np.hypot(c["vx"][i], c["vy"][i])) if known else 0.0
    heading = _heading(c, i, known and speed >= MOVING_MPS)
    kind, sub = CLASS_TO_SDSM.get(int(c["cls"][i]), ("unknown", 0))
    pos_bound = sw.Z95 * np.sqrt(max(c["cov_xx"][i], c["cov_yy"][i], 0.0))
    common: dict[str, Any] = {
        "objType": kind, "objTypeCfd": round(float(np.clip(c["confidence"][i], 0, 1)) * 100),
        "objectID": int(c["id"][i]) % 65536, "measurementTime": delta_ms, "timeConfidence": 0,
        "pos": {"offsetX": round(float(c["x"][i]) / 0.1), "offsetY": round(float(c["y"][i]) / 0.1)},
        "posConfidence": {"pos": _level(pos_bound, POSITION_LEVELS_M, POSITION_ENUM), "elevation": "unavailable"},
        "speed": min(round(speed / 0.02), 8190) if known else 8191,
        "speedConfidence": _level(sw.Z95 * np.sqrt(max(c["cov_vxx"][i], c["cov_vyy"][i])), SPEED_LEVELS_MPS,
                                  SPEED_ENUM) if known else "unavailable",
        # heading: clockwise from north, 0.0125 degree
        "heading": round(float((90.0 - np.degrees(heading)) % 360.0) / 0.0125) % 28800, "headingConf": "unavailable",
    }
    if c["z"][i]:
        common["pos"]["offsetZ"] = round(float(c["z"][i]) / 0.1)
    if c["ax"][i] or c["ay"][i] or c["yaw_rate"][i]:
        ch, sh = np.cos(heading), np.sin(heading)  # a_long = a . h, a_lat = a . h_perp (left)
        common["accel4way"] = {
            "long": _clip((c["ax"][i] * ch + c["ay"][i] * sh) / 0.01, -2000, 2000),
            "lat": _clip((-c["ax"][i] * sh + c["ay"][i] * ch) / 0.01, -2000, 2000),
            "vert": 0, "yaw": _clip(np.degrees(c["yaw_rate"][i]) / 0.01, -32767, 32767)}
    return {"detObjCommon": common, "detObjOptData": _detail(c, i, kind, sub)}


def _check(c: dict[str, np.ndarray], n: int, header: ObjectListHeader) -> None:
    if n == 0:
        raise EmptyList("an SDSM carries 1..255 objects, the list has none", "objects")
    if n > MAX_OBJECTS:
        raise InvalidMessage(f"objects: {n} objects, an SDSM carries at most {MAX_OBJECTS}", "objects")
    for name, col in c.items():
        if not np.isfinite(col).all():
            raise InvalidMessage(f"objects.{name} is not finite", f"objects.{name}")
    for name in ("x", "y", "z"):
        if (np.abs(np.rint(c[name] / 0.1)) > 32767).any():
            raise InvalidMessage(f"objects.{name} beyond the SDSM's +-{POSITION_RANGE_M} m", f"objects.{name}")
    if header.prediction_ns > 1_500_000_000:
        raise InvalidMessage("header.prediction_ns is beyond the SDSM's 1500 ms", "header.prediction_ns")


def encode(header: ObjectListHeader, objects: Any, station: int | None = None,
           origin_e7: tuple[int, int] = sw.SITE_ORIGIN_E7) -> bytes:
    """UPER SDSM of an RSU object list (positions in ``map``, 1..255 objects); ``station``: the
    4-byte source id as a number (default ``cpm.station_id(header.rsu_id)``)."""
    cols = sw.columns_of(objects)
    n = len(cols["id"])
    _check(cols, n, header)
    delta_ms = round(header.prediction_ns / 1e6)
    capture_ms = (header.capture_time_ns + 500_000) // 1_000_000
    publish_ms = (header.publish_time_ns + 500_000) // 1_000_000
    message = {
        "msgCnt": header.seq % 128,
        "sourceID": (station_id(header.rsu_id) if station is None else station).to_bytes(4, "big"),
        "equipmentType": "rsu", "sDSMTimeStamp": _time(header.capture_time_ns),
        "refPos": {"lat": origin_e7[0], "long": origin_e7[1]},
        "refPosXYConf": {"semiMajor": 255, "semiMinor": 255, "orientation": 65535},
        "objects": [_object(cols, i, delta_ms) for i in range(n)],
        "v2iSequence": header.seq, "v2iPublishDelta": min(max(publish_ms - capture_ms, 0), 65535),
    }
    return sw.asn1_encode(_spec(), "SensorDataSharingMessage", message, "sdsm")


# ---------------------------------------------------------------- decode


def _sigma(name: str, levels: tuple[float, ...], names: tuple[str, ...], unavailable: float) -> float:
    return levels[names.index(name)] / sw.Z95 if name in names else unavailable


def _fill(cols: dict[str, np.ndarray], i: int, obj: dict, ref_xy: tuple[float, float]) -> None:
    """Row ``i`` of the object columns from one decoded DetectedObjectData."""
    c = obj["detObjCommon"]
    cols["id"][i] = c["objectID"]
    cols["x"][i] = ref_xy[0] + c["pos"]["offsetX"] * 0.1
    cols["y"][i] = ref_xy[1] + c["pos"]["offsetY"] * 0.1
    cols["z"][i] = c["pos"].get("offsetZ", 0) * 0.1
    s = _sigma(c["posConfidence"]["pos"], POSITION_LEVELS_M, POSITION_ENUM, 100.0)
    cols["cov_xx"][i] = cols["cov_yy"][i] = s * s
    heading = np.radians(90.0 - c["heading"] * 0.0125) if c["heading"] < 28800 else 0.0
    cols["yaw"][i] = (heading + np.pi) % (2 * np.pi) - np.pi
    if c["speed"] < 8191 and c["speedConfidence"] != "unavailable":
        speed = c["speed"] * 0.02
        cols["vx"][i], cols["vy"][i] = speed * np.cos(heading), speed * np.sin(heading)
        sv = _sigma(c["speedConfidence"], SPEED_LEVELS_MPS, SPEED_ENUM, 100.0)
        cols["cov_vxx"][i] = cols["cov_vyy"][i] = min(sv * sv, UNKNOWN_VELOCITY_VAR)
    acc = c.get("accel4way")
    if acc is not None:
        a_long = 0.0 if acc["long"] == 2001 else acc["long"] * 0.01
        a_lat = 0.0 if acc["lat"] == 2001 else acc["lat"] * 0.01
        ch, sh = np.cos(heading), np.sin(heading)
        cols["ax"][i], cols["ay"][i] = a_long * ch - a_lat * sh, a_long * sh + a_lat * ch
        cols["yaw_rate"][i] = np.radians(acc["yaw"] * 0.01)
    cols["confidence"][i] = min(c["objTypeCfd"], 100) / 100.0
    _fill_detail(cols, i, c["objType"], obj.get("detObjOptData"))


def _fill_detail(cols: dict[str, np.ndarray], i: int, kind: str, detail: tuple | None) -> None:
    """Class and size of row ``i`` from objType and the optional vehicle / VRU / obstacle data."""
    name, d = detail if detail is not None else (None, {})
    if name == "detVeh":
        size = d.get("size", {"width": 180, "length": 450})
        cols["width"][i], cols["length"][i] = size["width"] * 0.01, size["length"] * 0.01
        cols["height"][i] = d.get("height", 30) * 0.05
        cols["cls"][i] = _FROM_SDSM.get(("vehicle", d.get("vehicleClass", 10)), ObjectClass.CAR)
    elif name == "detVRU":
        cols["length"][i] = cols["width"][i] = 2 * d.get("radius", 3) * 0.1
        cols["cls"][i] = _FROM_SDSM.get(("vru", d.get("basicType", 1)), ObjectClass.PEDESTRIAN)
    elif name == "detObst":
        size = d["obstSize"]
        cols["width"][i], cols["length"][i] = size["width"] * 0.1, size["length"] * 0.1
        cols["height"][i] = size.get("height", 15) * 0.1
        cols["cls"][i] = ObjectClass.UNKNOWN
    else:
        cols["cls"][i] = {"vehicle": ObjectClass.CAR, "vru": ObjectClass.PEDESTRIAN}.get(kind, ObjectClass.UNKNOWN)


@sw.guarded("sdsm")
def decode(data: bytes, rsu_id: str | None = None, max_bytes: int = sw.MAX_STANDARD_BYTES,
           origin_e7: tuple[int, int] | None = None) -> tuple[ObjectListHeader, dict[str, np.ndarray]]:
    """(header, object columns) of a UPER SDSM; ``rsu_id`` as in ``cpm.decode``; ``origin_e7``: the
    receiver's site origin (None: the message's own reference position). Every failure is a CodecError."""
    msg = sw.asn1_decode(_spec(), "SensorDataSharingMessage", sw.check_size(data, max_bytes, "sdsm"), "sdsm")
    objects = msg["objects"]
    deltas = {o["detObjCommon"]["measurementTime"] for o in objects}
    if len(deltas) > 1:
        raise InvalidMessage(f"sdsm objects measured at {len(deltas)} different times; a v2i list has one", "objects")
    delta_ms = deltas.pop()
    stamp_ms = _unix_ms(msg["sDSMTimeStamp"])
    capture_ms = stamp_ms + min(delta_ms, 0)
    ref = msg["refPos"]
    if ref["lat"] > 900_000_000 or ref["long"] > 1_800_000_000:
        raise InvalidMessage("sdsm reference position unavailable", "refPos")
    ref_xy = sw.geo_e7_to_map(ref["lat"], ref["long"], (ref["lat"], ref["long"]) if origin_e7 is None else origin_e7)
    cols = sw.empty_columns(len(objects))
    for i, obj in enumerate(objects):
        _fill(cols, i, obj, ref_xy)
    source = int.from_bytes(msg["sourceID"], "big")
    publish_ms = stamp_ms + msg.get("v2iPublishDelta", 0)
    hdr = sw.header(rsu_id or f"station{source}", msg.get("v2iSequence", stamp_ms), capture_ms * 1_000_000,
                    max(publish_ms, capture_ms) * 1_000_000, max(delta_ms, 0) * 1_000_000, SENSOR)
    return hdr, cols
