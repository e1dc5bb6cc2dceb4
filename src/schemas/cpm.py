"""RSU object lists as collective perception messages (ETSI TS 103 324 V2.1.1, CPM release 2), UPER,
byte-compatible with the published modules (``asn1/V2I-CPM.asn``; docs/messages.md).

- ``encode(header, objects, origin=...) -> bytes``: a v2i list (positions in ``map``) as a CPM;
- ``read(data) -> Reading``: any valid CPM in its own frame (what ``v2i wire decode`` prints),
  what v2i cannot use skipped and counted, an invalid one refused (``InvalidMessage`` /
  ``MalformedMessage``);
- ``decode(data, rsu_id, origin=...) -> (header, columns)``: a CPM placed in the receiver's
  ``map`` (``place``); one that cannot be placed is refused with the reason.

Mapping (v2i -> CPM; decode is the inverse, at the CPM's resolution):

==========================  =================================================  ======================
v2i                         CPM                                                quantisation / range
==========================  =================================================  ======================
rsu_id                      header.stationId (``station_id``, default crc32)   decode: the key's id
publish_time_ns             managementContainer.referenceTime (TAI)            1 ms (``its_time``)
capture + prediction        perceivedObject.measurementDeltaTime               1 ms after referenceTime
seq                         (none) decode: 8 referenceTime + segment - 1       time-derived
site origin (``map`` 0, 0)  managementContainer.referencePosition              0.1 microdegree
id                          objectId                                           modulo 65536
x, y, z                     position.{x,y,z}Coordinate.value (east, north, up)  0.01 m, +-1310.7 m
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
cls                         classification (``CLASS_TO_CPM``)                  nearest ETSI class
==========================  =================================================  ======================
"""

from __future__ import annotations

import zlib
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from schemas import its_time
from schemas import standard_wire as sw
from schemas.codec import InvalidMessage, WrongMessageType
from schemas.cpm_objects import CLASS_TO_CPM, check_columns, code_columns, object_of, read_objects
from schemas.messages import UNKNOWN_VELOCITY_VAR, ObjectListHeader

ASN1_FILE = "V2I-CPM.asn"
MESSAGE_ID = 14
PROTOCOL_VERSION = 2
VEHICLE_CONTAINER, RSU_CONTAINER, SENSOR_CONTAINER, REGION_CONTAINER, OBJECT_CONTAINER = 1, 2, 3, 4, 5
CONTAINER_TYPES = {VEHICLE_CONTAINER: "OriginatingVehicleContainer", RSU_CONTAINER: "OriginatingRsuContainer",
                   SENSOR_CONTAINER: "SensorInformationContainer", REGION_CONTAINER: "PerceptionRegionContainer",
                   OBJECT_CONTAINER: "PerceivedObjectContainer"}
MAX_CPM_OBJECTS = MAX_OBJECTS = 255
POSITION_LIMIT = 131070  # 0.01 m codes; 131071 / -131072 mean out of range
POSITION_RANGE_M = POSITION_LIMIT * 0.01
LAT_UNAVAILABLE, LON_UNAVAILABLE = 900_000_001, 1_800_000_001
SENSOR = "cpm"
ORIGIN_DEG = (0.0, 0.0)  # a site's WGS84 origin when none is given


def station_id(rsu_id: str) -> int:
    """Default ETSI station id of an RSU id: CRC-32 of its name."""
    return zlib.crc32(rsu_id.encode())


def _spec():
    return sw.compiled(ASN1_FILE)


def _e7(deg: float) -> int:
    return int(round(deg * 1e7))


# ---------------------------------------------------------------- encode


def _reference_ms(header: ObjectListHeader) -> tuple[int, int]:
    """(referenceTime, measurementDeltaTime): the publish time in TAI ms, moved (rarely) so that the
    objects' time (capture + prediction) is within the 2047 ms the delta can say."""
    valid_ms = its_time.its_ms(header.capture_time_ns + header.prediction_ns)
    reference = min(max(its_time.its_ms(header.publish_time_ns), valid_ms - 2047), valid_ms + 2048)
    return reference, valid_ms - reference


def encode(header: ObjectListHeader, objects: Any, station: int | None = None,
           origin: tuple[float, float] | None = None) -> bytes:
    """UPER CPM of an RSU object list (positions in ``map``, whose origin is ``origin``: the site's
    WGS84 latitude, longitude in degrees). ``station``: ETSI station id (default
    ``station_id(header.rsu_id)``). Raises InvalidMessage for what a CPM cannot carry."""
    cols = sw.columns_of(objects)
    n = len(cols["id"])
    check_columns(cols, n)
    reference_ms, delta_ms = _reference_ms(header)
    codes = code_columns(cols)
    spec = _spec()
    container = {"numberOfPerceivedObjects": n, "perceivedObjects": [object_of(codes, i, delta_ms) for i in range(n)]}
    lat, lon = origin or ORIGIN_DEG
    management = {
        "referenceTime": reference_ms,
        "referencePosition": {"latitude": _e7(lat), "longitude": _e7(lon),
                              "positionConfidenceEllipse": {"semiMajorConfidence": 4095, "semiMinorConfidence": 4095,
                                                            "semiMajorOrientation": 3601},
                              "altitude": {"altitudeValue": 800001, "altitudeConfidence": "unavailable"}},
    }
    wrapped = [{"containerId": RSU_CONTAINER, "containerData": sw.asn1_encode(spec, "OriginatingRsuContainer", {}, "cpm")},
               {"containerId": OBJECT_CONTAINER,
                "containerData": sw.asn1_encode(spec, "PerceivedObjectContainer", container, "cpm")}]
    message = {"header": {"protocolVersion": PROTOCOL_VERSION, "messageId": MESSAGE_ID,
                          "stationId": station_id(header.rsu_id) if station is None else station},
               "payload": {"managementContainer": management, "cpmContainers": wrapped}}
    return sw.asn1_encode(spec, "CollectivePerceptionMessage", message, "cpm")


# ---------------------------------------------------------------- read


@dataclass
class Reading:
    """A CPM as read, in its own frame: x, y east / north of the reference position (an RSU's), or
    along / left of the originating vehicle's x axis, which points ``orientation_deg`` clockwise
    from north (a vehicle's). ``columns``: object columns (``standard_wire``) in that frame;
    ``delta_ms``: each object's measurementDeltaTime; ``skipped``: what v2i read past, by kind."""

    station_id: int
    reference_time_ms: int  # TimestampIts
    lat_deg: float | None  # None: unavailable
    lon_deg: float | None
    originator: str  # "rsu", "vehicle" or "unknown" (neither container)
    orientation_deg: float | None  # vehicle: its x axis, clockwise from north; None: unavailable
    columns: dict[str, np.ndarray]
    delta_ms: np.ndarray
    skipped: Counter = field(default_factory=Counter)
    segment: tuple[int, int] | None = None  # (thisMsgNo, totalMsgNo)
    beyond: list[dict] = field(default_factory=list)  # objects only "out of range" in x or y: id, x_m, y_m (bounds)
    root_size: bool = False  # read with the container list's size constraint without its extension bit


def _top(spec, data: bytes) -> tuple[dict, bool]:
    """The decoded message and whether it needed the extension-bit-less container list (X.691 reading
    of asn1c stacks; docs/messages.md)."""
    try:
        return spec.decode("CollectivePerceptionMessage", data, check_constraints=True), False
    except Exception:  # noqa: BLE001 - untrusted bytes: try the other reading, then refuse
        pass
    return sw.asn1_decode(spec, "CollectivePerceptionMessageRootSize", data, "cpm"), True


def _read_whole(spec, type_name: str, value: dict, data: bytes) -> bool:
    """Whether the decoded ``value`` accounts for all of ``data``: its UPER encoding (canonical) is as
    long. Shorter: the bytes carried what the decoder read past (extension additions it does not
    know, or trailing octets), counted as ``unread_<type>``; padding bits are not compared."""
    try:
        return len(spec.encode(type_name, value)) >= len(data)
    except Exception:  # noqa: BLE001
        return False


def _containers(spec, wrapped: list[dict], skipped: Counter, count_unread: bool) -> dict[int, Any]:
    """Containers 1-5 decoded by id; others skipped and counted. Refuses a repeated container and a
    message with both originating containers. ``count_unread``: check each container for octets
    read past (an encode more: the OBU's path leaves it out)."""
    found: dict[int, Any] = {}
    for c in wrapped:
        cid = c["containerId"]
        if cid in found:
            raise InvalidMessage(f"cpm container {cid} appears twice", "cpmContainers")
        if cid not in CONTAINER_TYPES:
            skipped[f"container_{cid}"] += 1
            found[cid] = None
            continue
        name = CONTAINER_TYPES[cid]
        found[cid] = sw.asn1_decode(spec, name, c["containerData"], f"cpm {name}")
        if count_unread and not _read_whole(spec, name, found[cid], c["containerData"]):
            skipped[f"unread_{name}"] += 1
    if VEHICLE_CONTAINER in found and RSU_CONTAINER in found:
        raise InvalidMessage("cpm has both an originating vehicle and an originating RSU container", "cpmContainers")
    for cid, kind in ((SENSOR_CONTAINER, "sensor_information"), (REGION_CONTAINER, "perception_region")):
        if found.get(cid) is not None:
            skipped[kind] += 1  # valid, not used by v2i
    return found


@sw.guarded("cpm")
def read(data: bytes, max_bytes: int = sw.MAX_STANDARD_BYTES, count_unread: bool = True) -> Reading:
    """A UPER CPM in its own frame (``Reading``). ``count_unread``: count extension additions and
    trailing octets that the decoder read past (``unread_<type>``; costs an encode of the message,
    which ``decode`` spares the OBU). Every failure is a CodecError."""
    spec = _spec()
    raw = sw.check_size(data, max_bytes, "cpm")
    msg, root_size = _top(spec, raw)
    head, payload = msg["header"], msg["payload"]
    if head["messageId"] != MESSAGE_ID or head["protocolVersion"] != PROTOCOL_VERSION:
        raise WrongMessageType(f"ITS message id {head['messageId']} version {head['protocolVersion']} received "
                               f"where a CPM (id {MESSAGE_ID}, version {PROTOCOL_VERSION}) was expected")
    skipped: Counter = Counter()
    top_type = "CollectivePerceptionMessageRootSize" if root_size else "CollectivePerceptionMessage"
    if count_unread and not _read_whole(spec, top_type, msg, raw):
        skipped["unread_CollectivePerceptionMessage"] += 1
    found = _containers(spec, payload["cpmContainers"], skipped, count_unread)
    management = payload["managementContainer"]
    position = management["referencePosition"]
    lat, lon = position["latitude"], position["longitude"]
    vehicle = found.get(VEHICLE_CONTAINER)
    orientation = None
    if vehicle is not None and vehicle["orientationAngle"]["value"] < 3600:
        orientation = vehicle["orientationAngle"]["value"] * 0.1
    objects = (found.get(OBJECT_CONTAINER) or {}).get("perceivedObjects", [])
    beyond: list[dict] = []
    columns, delta_ms = read_objects(objects, skipped, beyond)
    segment = management.get("segmentationInfo")
    return Reading(
        station_id=head["stationId"], reference_time_ms=management["referenceTime"],
        lat_deg=None if lat == LAT_UNAVAILABLE else lat / 1e7, lon_deg=None if lon == LON_UNAVAILABLE else lon / 1e7,
        originator="vehicle" if VEHICLE_CONTAINER in found else "rsu" if RSU_CONTAINER in found else "unknown",
        orientation_deg=orientation, columns=columns, delta_ms=delta_ms, skipped=skipped,
        segment=None if segment is None else (segment["thisMsgNo"], segment["totalMsgNo"]), root_size=root_size,
        beyond=beyond)


def shifted(data: bytes, shift_ms: int) -> bytes:
    """The CPM ``data`` with its referenceTime moved by ``shift_ms`` (every time in a CPM is relative
    to it), all else byte for byte as decoded (a replay's time shift). CodecError if unreadable."""
    spec = _spec()
    msg, root_size = _top(spec, sw.check_size(data, sw.MAX_STANDARD_BYTES, "cpm"))
    management = msg["payload"]["managementContainer"]
    management["referenceTime"] += int(shift_ms)
    top = "CollectivePerceptionMessageRootSize" if root_size else "CollectivePerceptionMessage"
    return sw.asn1_encode(spec, top, msg, "cpm")


# ---------------------------------------------------------------- place


def _rotate(cols: dict[str, np.ndarray], theta: float) -> None:
    """Rotate positions, velocities, accelerations, yaw and covariances counter-clockwise by theta (rad)."""
    c, s = np.cos(theta), np.sin(theta)
    for a, b in (("x", "y"), ("vx", "vy"), ("ax", "ay")):
        cols[a], cols[b] = c * cols[a] - s * cols[b], s * cols[a] + c * cols[b]
    cols["yaw"] = np.mod(cols["yaw"] + theta + np.pi, 2 * np.pi) - np.pi
    for xx, xy, yy in (("cov_xx", "cov_xy", "cov_yy"), ("cov_vxx", "cov_vxy", "cov_vyy")):
        # C' = R C R^T
        a, b, d = cols[xx], cols[xy], cols[yy]
        cols[xx] = c * c * a - 2 * c * s * b + s * s * d
        cols[yy] = s * s * a + 2 * c * s * b + c * c * d
        cols[xy] = c * s * (a - d) + (c * c - s * s) * b


def place(reading: Reading, origin: tuple[float, float] | None = None) -> dict[str, np.ndarray]:
    """The reading's objects in ``map`` (east-north-up at ``origin``, the receiver's site origin in
    degrees; None: at the message's reference position), all at the latest object time (each moved
    there at its velocity). Refuses (InvalidMessage, naming the reason) a CPM that cannot be placed:
    no reference position, or a vehicle's without its orientation."""
    from schemas import enu

    if reading.lat_deg is None or reading.lon_deg is None:
        raise InvalidMessage("cpm cannot be placed: reference position unavailable", "referencePosition")
    cols = {k: v.copy() for k, v in reading.columns.items()}
    if reading.originator == "vehicle":
        if reading.orientation_deg is None:
            raise InvalidMessage("cpm cannot be placed: originating vehicle's orientation unavailable",
                                 "originatingVehicleContainer.orientationAngle")
        # vehicle x axis at heading h (clockwise from north) is at 90 - h degrees counter-clockwise from east
        _rotate(cols, np.radians(90.0 - reading.orientation_deg))
    ref = (reading.lat_deg, reading.lon_deg)
    o = ref if origin is None else origin
    if ref != o:  # east / north of the reference -> east / north of the receiver's origin (through ECEF)
        cols["x"], cols["y"] = enu.between(cols["x"], cols["y"], ref, o)
    if len(reading.delta_ms):
        dt = (reading.delta_ms.max() - reading.delta_ms) * 1e-3
        known = cols["cov_vxx"] < UNKNOWN_VELOCITY_VAR
        cols["x"] = cols["x"] + np.where(known, cols["vx"] * dt, 0.0)
        cols["y"] = cols["y"] + np.where(known, cols["vy"] * dt, 0.0)
    return cols


def sequence(reference_ms: int, segment: int = 0) -> int:
    """The v2i sequence number of a CPM (it has none): 8 referenceTime + (thisMsgNo - 1), unique and
    increasing per station, segments of one generation event included."""
    return 8 * int(reference_ms) + int(segment)


@sw.guarded("cpm")
def decode(data: bytes, rsu_id: str | None = None, max_bytes: int = sw.MAX_STANDARD_BYTES,
           origin: tuple[float, float] | None = None) -> tuple[ObjectListHeader, dict[str, np.ndarray]]:
    """(header, object columns in ``map``) of a UPER CPM; ``origin``: the receiver's site origin (lat,
    lon degrees). ``rsu_id``: the id the message came under (its key); None names the RSU
    ``station<stationId>``. Header: publish = referenceTime, capture = the latest object time,
    prediction 0, seq = ``sequence`` (from referenceTime and the segment). Every failure is a CodecError."""
    reading = read(data, max_bytes, count_unread=False)
    cols = place(reading, origin)
    reference_ms = reading.reference_time_ms
    capture_ms = reference_ms + (int(reading.delta_ms.max()) if len(reading.delta_ms) else 0)
    capture_ns, publish_ns = its_time.unix_ns(capture_ms), its_time.unix_ns(reference_ms)
    if capture_ns < 0 or publish_ns < 0:
        raise InvalidMessage(f"cpm referenceTime {reference_ms} is before 1970", "referenceTime")
    segment = 0 if reading.segment is None else reading.segment[0] - 1
    hdr = sw.header(rsu_id or f"station{reading.station_id}", sequence(reference_ms, segment), capture_ns,
                    max(publish_ns, capture_ns), 0, SENSOR)
    return hdr, cols


__all__ = ["CLASS_TO_CPM", "Reading", "decode", "encode", "place", "read", "station_id"]
