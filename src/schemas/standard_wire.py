"""What the standard encodings (``schemas.cpm``, ``schemas.sdsm``) share: the ASN.1 compiled
once, untrusted bytes decoded into the codec's error family, object columns, site geometry.

Object columns are a ``dict`` of ``(N,)`` float64 arrays named as the codec's object columns
(``schemas.codec.OBJECT_COLUMNS``: ``id, cls, x, y, z, length, width, height, yaw, vx, vy,
ax, ay, yaw_rate, cov_xx, cov_xy, cov_yy, cov_vxx, cov_vxy, cov_vyy, confidence, age_s``;
metres, m/s, m/s^2, rad, rad/s, m^2, m^2/s^2, s). ``columns_of`` reads them from an
``ObjectArray`` (duck-typed: ``schemas`` does not import ``fusion``), from wire objects, or
from such a dict; ``object_list`` builds the validated ``ObjectList`` the OBU accepts.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from schemas.codec import CodecError, InvalidMessage, MalformedMessage, MessageTooLarge
from schemas.messages import UNKNOWN_VELOCITY_VAR, ObjectList, ObjectListHeader, ObjectState

ASN1_DIR = Path(__file__).with_name("asn1")
COLUMN_NAMES = ("id", "cls", "x", "y", "z", "length", "width", "height", "yaw", "vx", "vy", "ax", "ay", "yaw_rate",
                "cov_xx", "cov_xy", "cov_yy", "cov_vxx", "cov_vxy", "cov_vyy", "confidence", "age_s")
# 2004-01-01T00:00:00Z in Unix ms: the epoch of ETSI TimestampIts (leap seconds not counted here:
# both ends of a v2i link use Unix time, and the OBU's clock sync absorbs a constant offset)
ITS_EPOCH_MS = 1_072_915_200_000
EARTH_RADIUS_M = 6_371_000.0
MAX_STANDARD_BYTES = 1 << 16
# A site's geodetic origin (latitude, longitude in 0.1 microdegree): the map frame's (0, 0).
# Both ends of a link must agree; a position is sent as an offset from it (x east, y north).
SITE_ORIGIN_E7 = (0, 0)
Z95 = 1.959963984540054  # two-sided 95 % quantile of the normal law: confidence = Z95 * sigma


@cache
def compiled(filename: str) -> Any:
    """The UPER codec of an ASN.1 file in ``asn1/``, compiled once per process (~0.3 s of CPU:
    a service does it before it is ready, ``list_wire.prepare``)."""
    import asn1tools  # imported on first use: a v2i-only process never pays for it

    return asn1tools.compile_files(str(ASN1_DIR / filename), "uper")


def asn1_decode(spec: Any, type_name: str, data: bytes, what: str) -> dict:
    """``spec.decode`` of untrusted bytes; every failure a MalformedMessage (asn1tools raises its own
    errors and, on some hostile lengths, NotImplementedError or IndexError: any exception of the
    parser on untrusted bytes means the bytes are not a message it can read)."""
    try:
        return spec.decode(type_name, bytes(data), check_constraints=True)
    except Exception as exc:  # noqa: BLE001 - see the docstring
        detail = f"{type(exc).__name__}: {str(exc)[:80]}"
        raise MalformedMessage(f"{what}: not a valid UPER {type_name} ({detail})") from None


def asn1_encode(spec: Any, type_name: str, value: dict, what: str) -> bytes:
    """``spec.encode``; a value the ASN.1 refuses is an InvalidMessage (a mapping bug or a bad input)."""
    import asn1tools

    try:
        return spec.encode(type_name, value, check_constraints=True)
    except (asn1tools.Error, ValueError, TypeError, KeyError, OverflowError) as exc:
        raise InvalidMessage(f"{what}: cannot encode {type_name} ({type(exc).__name__}: {str(exc)[:120]})") from None


def check_size(data: Any, max_bytes: int, what: str) -> bytes:
    """The payload as bytes, after the size bound (checked before any parsing)."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"decode() takes bytes, got {type(data).__name__}")
    size = memoryview(data).nbytes
    if size > max_bytes:
        raise MessageTooLarge(f"{what} payload is {size} bytes, limit is {max_bytes}")
    if size == 0:
        raise MalformedMessage(f"{what} payload is empty")
    return bytes(data)


def guarded(what: str) -> Callable:
    """Decorator: any non-codec exception of a decoder (a mapping that meets an impossible value)
    becomes a MalformedMessage, so hostile bytes only ever give a counted rejection."""

    def wrap(fn: Callable) -> Callable:
        def inner(*args, **kwargs):
            try:
                return fn(*args, **kwargs)
            except CodecError:
                raise
            except (ValueError, TypeError, KeyError, IndexError, AttributeError, OverflowError, ArithmeticError,
                    RecursionError, NotImplementedError) as exc:
                raise MalformedMessage(f"{what}: {type(exc).__name__}: {str(exc)[:80]}") from None

        inner.__name__, inner.__doc__ = fn.__name__, fn.__doc__
        return inner

    return wrap


# ---------------------------------------------------------------- columns


def columns_of(objects: Any) -> dict[str, np.ndarray]:
    """Object columns (module docstring) of an ObjectArray, a sequence of ObjectState, or a dict."""
    if isinstance(objects, dict):
        return {k: np.asarray(objects[k], dtype=np.float64) for k in COLUMN_NAMES}
    if hasattr(objects, "codes") and hasattr(objects, "column"):  # schemas.columns.ObjectColumns
        return {k: objects.column(k).astype(np.float64) for k in COLUMN_NAMES}
    if hasattr(objects, "xy"):  # v2i.core.objects.ObjectArray
        o = objects
        return {
            "id": o.ids.astype(np.float64), "cls": o.cls.astype(np.float64), "x": o.xy[:, 0], "y": o.xy[:, 1],
            "z": o.z, "length": o.lwh[:, 0], "width": o.lwh[:, 1], "height": o.lwh[:, 2], "yaw": o.yaw,
            "vx": o.vxy[:, 0], "vy": o.vxy[:, 1], "ax": o.axy[:, 0], "ay": o.axy[:, 1], "yaw_rate": o.yaw_rate,
            "cov_xx": o.cov_xy[:, 0, 0], "cov_xy": o.cov_xy[:, 0, 1], "cov_yy": o.cov_xy[:, 1, 1],
            "cov_vxx": o.cov_vxy[:, 0, 0], "cov_vxy": o.cov_vxy[:, 0, 1], "cov_vyy": o.cov_vxy[:, 1, 1],
            "confidence": o.confidence, "age_s": o.age_s,
        }
    states: Sequence[ObjectState] = tuple(objects)
    return {k: np.array([getattr(s, k) for s in states], dtype=np.float64) for k in COLUMN_NAMES}


def object_list(header: ObjectListHeader, columns: dict[str, np.ndarray]) -> ObjectList:
    """The validated ObjectList of a decoded header and columns (every v2i model rule)."""
    table = np.column_stack([columns[k] for k in COLUMN_NAMES]).reshape(len(columns["id"]), len(COLUMN_NAMES))
    try:
        from schemas.columns import ObjectColumns
    except ImportError:  # before the columnar object lists (schemas.columns): per-object models
        rows = [dict(zip(COLUMN_NAMES, row)) for row in table.tolist()]
        for row in rows:
            row["id"], row["cls"] = int(row["id"]), int(row["cls"])
        objects: Any = tuple(ObjectState(**row) for row in rows)
    else:
        objects = ObjectColumns.from_values(table)
    try:
        return ObjectList(header=header, objects=objects)
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        loc = ".".join(map(str, err["loc"]))
        raise InvalidMessage(f"decoded standard message breaks a v2i rule: {loc}: {err['msg']}", loc) from None


def header(rsu_id: str, seq: int, capture_ns: int, publish_ns: int, prediction_ns: int,
           sensor: str) -> ObjectListHeader:
    """The validated v2i header of a decoded standard message."""
    try:
        return ObjectListHeader(rsu_id=rsu_id, seq=seq, capture_time_ns=capture_ns, publish_time_ns=publish_ns,
                                prediction_ns=prediction_ns, sensor=sensor)
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        loc = ".".join(map(str, err["loc"]))
        raise InvalidMessage(f"decoded standard header breaks a v2i rule: {loc}: {err['msg']}",
                             f"header.{loc}") from None


def empty_columns(n: int) -> dict[str, np.ndarray]:
    """Columns of ``n`` objects at the v2i defaults (unit position variance, unknown velocity)."""
    cols = {k: np.zeros(n) for k in COLUMN_NAMES}
    cols["cov_xx"][:] = cols["cov_yy"][:] = 1.0
    cols["cov_vxx"][:] = cols["cov_vyy"][:] = UNKNOWN_VELOCITY_VAR
    cols["confidence"][:] = 1.0
    cols["height"][:] = 1.5
    return cols


# ---------------------------------------------------------------- site geometry


def map_to_geo_e7(x_m: float, y_m: float, origin_e7: tuple[int, int] = SITE_ORIGIN_E7) -> tuple[int, int]:
    """(lat, lon) in 0.1 microdegree of a map point: local equirectangular projection about the origin,
    lat = lat0 + y / R, lon = lon0 + x / (R cos lat0) (radians; error < 1 cm within a few km)."""
    lat0_rad = math.radians(origin_e7[0] * 1e-7)
    lat = origin_e7[0] + round(math.degrees(y_m / EARTH_RADIUS_M) * 1e7)
    lon = origin_e7[1] + round(math.degrees(x_m / (EARTH_RADIUS_M * math.cos(lat0_rad))) * 1e7)
    return lat, lon


def geo_e7_to_map(lat_e7: int, lon_e7: int, origin_e7: tuple[int, int] = SITE_ORIGIN_E7) -> tuple[float, float]:
    """Map (x, y) metres of a (lat, lon) in 0.1 microdegree: the inverse of ``map_to_geo_e7``."""
    lat0_rad = math.radians(origin_e7[0] * 1e-7)
    y = math.radians((lat_e7 - origin_e7[0]) * 1e-7) * EARTH_RADIUS_M
    x = math.radians((lon_e7 - origin_e7[1]) * 1e-7) * EARTH_RADIUS_M * math.cos(lat0_rad)
    return x, y


def its_ms(t_ns: int) -> int:
    """Milliseconds since 2004-01-01 (ETSI TimestampIts) of a Unix time in ns, rounded."""
    return (int(t_ns) + 500_000) // 1_000_000 - ITS_EPOCH_MS
