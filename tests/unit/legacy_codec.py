"""Today's codec before schema 4 (kept for tests and benchmarks only): msgpack map envelope,
fixed-width object columns, every object decoded into a pydantic model.

A copy of ``src/schemas/codec.py`` at schema version 3, with its object-list models
(``ObjectList``/``FusedObjectList`` holding tuples of ``ObjectState``/``FusedObject``); its
envelope states the current SCHEMA_VERSION so that the shared header model accepts it.
The differential test (``test_wire_differential``) holds the new decoder to its verdicts.

Original docstring: versioned msgpack envelope, columnar object tuples, validated decode.

Wire layout::

    {"v": SCHEMA_VERSION, "t": Model.TYPE, "d": body}

``body`` is the model's ``model_dump(mode="python")``, except that the object tuple of
an :class:`ObjectList` / :class:`FusedObjectList` becomes a map of columns
``{"n": count, "x": bytes, ...}``: each column is a little-endian integer array of the
quantisation codes (``quantize.code(value, step)``). The models already hold grid values
``k * step`` and decoding computes ``k * step`` again, so ``decode(encode(m)) == m`` exactly.

Every failure of :func:`decode` on untrusted bytes is a :class:`CodecError` whose
``reason`` is a short label fit for a rejection counter.
"""

from __future__ import annotations

import reprlib
from collections.abc import Sequence
from dataclasses import dataclass
from operator import attrgetter
from typing import Any, TypeVar

import msgpack
import numpy as np
from pydantic import ValidationError

from pydantic import Field

from schemas import quantize as q
from schemas.errors import (CodecError, InvalidMessage, MalformedMessage, MessageTooLarge, SchemaVersionError,
                            WrongMessageType)
from schemas.messages import (MAX_OBJECTS, SCHEMA_VERSION, FusedObject, Message, NodeId, ObjectListHeader, ObjectState,
                              Position, SchemaVersion, Seq, TimeNs, Yaw)
from typing import Annotated, ClassVar


class ObjectList(Message):
    TYPE: ClassVar[str] = "object_list"
    header: ObjectListHeader
    objects: Annotated[tuple[ObjectState, ...], Field(max_length=MAX_OBJECTS)] = ()


class FusedObjectList(Message):
    TYPE: ClassVar[str] = "fused_object_list"
    schema_version: SchemaVersion = SCHEMA_VERSION
    vehicle_id: NodeId
    seq: Seq
    cycle_time_ns: TimeNs
    publish_time_ns: TimeNs
    frame_id: Annotated[str, Field(max_length=64)] = "base_link"
    fusion: Annotated[str, Field(max_length=32)] = ""
    mode: Annotated[str, Field(max_length=32)] = ""
    ego_x: Position = 0.0
    ego_y: Position = 0.0
    ego_yaw: Yaw = 0.0
    objects: Annotated[tuple[FusedObject, ...], Field(max_length=MAX_OBJECTS)] = ()

MAX_MESSAGE_BYTES = 1 << 20
# Largest msgpack array/map accepted. The unpacker pre-allocates a container from its
# declared length, so this bounds the memory a tiny hostile payload can claim.
MAX_CONTAINER_LEN = 4096
ENVELOPE_KEYS = frozenset({"v", "t", "d"})

M = TypeVar("M", bound=Message)


@dataclass(frozen=True)
class Column:
    """One object attribute on the wire: ``dtype`` little-endian code, ``step`` grid (None: integer)."""

    name: str
    dtype: np.dtype
    step: float | None = None

    @property
    def bounds(self) -> tuple[int, int]:
        """Smallest and largest code the dtype can hold."""
        info = np.iinfo(self.dtype)
        return int(info.min), int(info.max)


def _col(name: str, dtype: str, step: float | None = None) -> Column:
    return Column(name, np.dtype(dtype), step)


OBJECT_COLUMNS: tuple[Column, ...] = (
    _col("id", "<u4"),
    _col("cls", "u1"),
    _col("x", "<i4", q.POSITION_M),
    _col("y", "<i4", q.POSITION_M),
    _col("z", "<i4", q.POSITION_M),
    _col("length", "<u2", q.SIZE_M),
    _col("width", "<u2", q.SIZE_M),
    _col("height", "<u2", q.SIZE_M),
    _col("yaw", "<i2", q.YAW_RAD),
    _col("vx", "<i2", q.SPEED_MPS),
    _col("vy", "<i2", q.SPEED_MPS),
    _col("ax", "<i2", q.ACCEL_MPS2),
    _col("ay", "<i2", q.ACCEL_MPS2),
    _col("yaw_rate", "<i2", q.YAW_RATE_RADPS),
    _col("cov_xx", "<u4", q.COV_M2),
    _col("cov_xy", "<i4", q.COV_M2),
    _col("cov_yy", "<u4", q.COV_M2),
    _col("cov_vxx", "<u4", q.COV_M2),
    _col("cov_vxy", "<i4", q.COV_M2),
    _col("cov_vyy", "<u4", q.COV_M2),
    _col("confidence", "u1", q.CONFIDENCE),
    _col("age_s", "<u4", q.AGE_S),
)
FUSED_OBJECT_COLUMNS: tuple[Column, ...] = (*OBJECT_COLUMNS, _col("sources", "u1"))

# Message TYPE -> columns of its ``objects`` tuple.
COLUMNAR: dict[str, tuple[Column, ...]] = {
    ObjectList.TYPE: OBJECT_COLUMNS,
    FusedObjectList.TYPE: FUSED_OBJECT_COLUMNS,
}

_short = reprlib.Repr()
_short.maxstring = 40
_short.maxother = 40
_short.maxlevel = 2


# ---------------------------------------------------------------- columns


def _object_table(objects: Sequence[Any], columns: Sequence[Column]) -> np.ndarray:
    """(n, len(columns)) float64 array of the objects' attribute values."""
    getter = attrgetter(*(c.name for c in columns))
    try:
        table = np.array([getter(o) for o in objects], dtype=np.float64)
    except (AttributeError, TypeError, ValueError, OverflowError) as exc:
        raise InvalidMessage(f"objects: cannot read object attributes as numbers: {exc}", "objects") from exc
    return table.reshape(len(objects), len(columns))


def _column_codes(values: np.ndarray, col: Column) -> np.ndarray:
    """Integer codes of one column, range-checked before the cast (no silent wrap-around)."""
    codes = np.rint(values if col.step is None else values / col.step)
    lo, hi = col.bounds
    ok = np.isfinite(codes) & (codes >= lo) & (codes <= hi)
    if col.step is None:
        ok &= codes == values  # integer attributes must already be integers
    if not ok.all():
        i = int(np.flatnonzero(~ok)[0])
        raise InvalidMessage(
            f"objects.{i}.{col.name} = {values[i]!r} does not fit the wire column "
            f"({col.dtype.name}, step {col.step or 1}: codes {lo}..{hi})",
            f"objects.{i}.{col.name}",
        )
    return codes.astype(col.dtype)


def pack_columns(objects: Sequence[Any], columns: Sequence[Column]) -> dict[str, Any]:
    """``{"n": count, name: little-endian code bytes}`` for a tuple of objects."""
    if len(objects) > MAX_OBJECTS:
        raise InvalidMessage(f"objects: {len(objects)} objects, at most {MAX_OBJECTS} allowed", "objects")
    table = _object_table(objects, columns)
    packed: dict[str, Any] = {"n": len(objects)}
    for j, col in enumerate(columns):
        packed[col.name] = _column_codes(table[:, j], col).tobytes()
    return packed


def _column_count(packed: Any, columns: Sequence[Column]) -> int:
    """Validated object count of a column map (shape errors are MalformedMessage)."""
    if not isinstance(packed, dict):
        raise MalformedMessage(f"objects must be a column map, got {type(packed).__name__}")
    n = packed.get("n")
    if type(n) is not int or n < 0:
        raise MalformedMessage(f"objects column map needs a non-negative integer 'n', got {_short.repr(n)}")
    if n > MAX_OBJECTS:
        raise InvalidMessage(f"objects: {n} objects, at most {MAX_OBJECTS} allowed", "objects")
    expected = {"n", *(c.name for c in columns)}
    if packed.keys() != expected:
        missing = sorted(expected - packed.keys())
        extra = sorted(map(repr, packed.keys() - expected))
        raise MalformedMessage(f"objects column map: missing columns {missing}, unexpected {extra}")
    return n


def _column_values(buf: Any, n: int, col: Column) -> list:
    """Decoded values of one column: ints, or ``code * step`` floats."""
    size = n * col.dtype.itemsize
    if not isinstance(buf, bytes) or len(buf) != size:
        got = f"{len(buf)} bytes" if isinstance(buf, bytes) else type(buf).__name__
        raise MalformedMessage(
            f"objects column {col.name!r}: got {got}, expected {size} bytes ({n} x {col.dtype.name})"
        )
    codes = np.frombuffer(buf, dtype=col.dtype)
    # k * step in float64: the same arithmetic as quantize.quantize, hence bit-exact.
    return codes.tolist() if col.step is None else (codes * col.step).tolist()


def unpack_columns(packed: Any, columns: Sequence[Column]) -> list[dict[str, Any]]:
    """Per-object attribute dicts from a column map (inverse of :func:`pack_columns`)."""
    n = _column_count(packed, columns)
    names = [c.name for c in columns]
    values = [_column_values(packed[c.name], n, c) for c in columns]
    return [dict(zip(names, row)) for row in zip(*values)]


# ---------------------------------------------------------------- encode


def _body(msg: Message) -> dict[str, Any]:
    """Plain-data body of a message, object tuples packed as columns."""
    columns = COLUMNAR.get(msg.TYPE)
    if columns is None:
        return msg.model_dump(mode="python")
    body = msg.model_dump(mode="python", exclude={"objects"})
    body["objects"] = pack_columns(msg.objects, columns)
    return body


def encode(msg: Message, max_bytes: int = MAX_MESSAGE_BYTES) -> bytes:
    """msgpack bytes of ``msg`` in a versioned envelope, at most ``max_bytes`` long.

    Raises InvalidMessage if a value cannot be represented on the wire and
    MessageTooLarge if the result exceeds ``max_bytes``.
    """
    if not isinstance(msg, Message):
        raise TypeError(f"encode() takes a schemas Message, got {type(msg).__name__}")
    envelope = {"v": SCHEMA_VERSION, "t": msg.TYPE, "d": _body(msg)}
    try:
        data = msgpack.packb(envelope, use_bin_type=True)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InvalidMessage(f"cannot encode {msg.TYPE}: {exc}") from exc
    if len(data) > max_bytes:
        raise MessageTooLarge(f"encoded {msg.TYPE} is {len(data)} bytes, limit is {max_bytes}")
    return data


# ---------------------------------------------------------------- decode


def _unpack(data: bytes | bytearray | memoryview, size: int, max_bytes: int) -> Any:
    """One msgpack value from untrusted bytes, with container and buffer limits."""
    unpacker = msgpack.Unpacker(
        raw=False,
        strict_map_key=True,
        max_buffer_size=max(max_bytes, 1),
        max_array_len=MAX_CONTAINER_LEN,
        max_map_len=MAX_CONTAINER_LEN,
        max_ext_len=0,
    )
    try:
        unpacker.feed(data)
        value = unpacker.unpack()
    except msgpack.OutOfData:
        what = "payload is empty" if size == 0 else f"payload is truncated: {size} bytes end inside a msgpack value"
        raise MalformedMessage(what) from None
    except (msgpack.UnpackException, ValueError, TypeError, OverflowError, RecursionError, MemoryError) as exc:
        detail = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        raise MalformedMessage(f"payload is not valid msgpack ({detail})") from None
    if unpacker.tell() != size:
        raise MalformedMessage(f"payload has {size - unpacker.tell()} trailing bytes after the msgpack value")
    return value


def _open_envelope(envelope: Any, model: type[Message]) -> dict[str, Any]:
    """The body of a checked envelope: shape, then version, then type tag."""
    if not isinstance(envelope, dict) or envelope.keys() != ENVELOPE_KEYS:
        got = f"keys {sorted(map(repr, envelope))}" if isinstance(envelope, dict) else type(envelope).__name__
        raise MalformedMessage(f"envelope must be a map with keys 'v', 't', 'd', got {got[:80]}")
    version, tag, body = envelope["v"], envelope["t"], envelope["d"]
    if type(version) is not int:
        raise MalformedMessage(f"envelope version 'v' must be an integer, got {_short.repr(version)}")
    if version != SCHEMA_VERSION:
        raise SchemaVersionError(f"schema version {version} received, this build speaks version {SCHEMA_VERSION}")
    if type(tag) is not str:
        raise MalformedMessage(f"envelope type tag 't' must be a string, got {_short.repr(tag)}")
    if tag != model.TYPE:
        raise WrongMessageType(f"message type {_short.repr(tag)} received where {model.TYPE!r} was expected")
    if not isinstance(body, dict):
        raise MalformedMessage(f"envelope body 'd' must be a map, got {type(body).__name__}")
    return body


def _describe(exc: ValidationError, type_name: str, limit: int = 3) -> InvalidMessage:
    """InvalidMessage naming the first offending fields of a pydantic error."""
    errors = exc.errors(include_url=False)
    parts = []
    for err in errors[:limit]:
        loc = ".".join(str(p) for p in err["loc"]) or "<body>"
        parts.append(f"{loc}: {err['msg']} (got {_short.repr(err.get('input'))})")
    more = f" (+{len(errors) - limit} more)" if len(errors) > limit else ""
    first = ".".join(str(p) for p in errors[0]["loc"]) if errors else ""
    return InvalidMessage(f"invalid {type_name}: " + "; ".join(parts) + more, first)


def open_body(data: bytes, model: type[Message], max_bytes: int = MAX_MESSAGE_BYTES) -> dict[str, Any]:
    """The body map of wire bytes, checked up to (not including) any per-object work.

    Checks, in order: size (before unpacking), msgpack well-formedness, envelope shape,
    envelope schema version, type tag, and the schema version a body or header states.
    A receiver can look at the header (``header_of``) and the object count
    (``object_count``) before paying for ``from_body``.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"decode() takes bytes, got {type(data).__name__}")
    size = memoryview(data).nbytes
    if size > max_bytes:
        raise MessageTooLarge(f"{model.TYPE} payload is {size} bytes, limit is {max_bytes}")
    body = _open_envelope(_unpack(data, size, max_bytes), model)
    header = body.get("header")
    for holder in (body, header if isinstance(header, dict) else {}):
        stated = holder.get("schema_version", SCHEMA_VERSION)
        if type(stated) is int and stated != SCHEMA_VERSION:
            raise SchemaVersionError(f"{model.TYPE} states schema version {stated}, this build speaks "
                                     f"version {SCHEMA_VERSION}")
    return body


def header_of(body: dict[str, Any]) -> ObjectListHeader:
    """The validated header of an opened object or prediction list body (cheap: no objects)."""
    try:
        return ObjectListHeader.model_validate(body.get("header"))
    except ValidationError as exc:
        err = _describe(exc, ObjectListHeader.TYPE)
        raise InvalidMessage(f"header: {err}", f"header.{err.field}") from None


def object_count(body: dict[str, Any]) -> int:
    """Objects (and, for predictions, paths) an opened body declares, before any is decoded."""
    objects, paths = body.get("objects"), body.get("paths")
    n = objects.get("n") if isinstance(objects, dict) else None
    count = n if type(n) is int and n >= 0 else 0
    return max(count, len(paths)) if isinstance(paths, list) else count


def path_point_count(body: dict[str, Any]) -> int:
    """Predicted positions an opened prediction list carries (its size once decoded), before decoding."""
    paths = body.get("paths")
    if not isinstance(paths, list):
        return 0
    return sum(len(p["x"]) for p in paths if isinstance(p, dict) and isinstance(p.get("x"), list))


def from_body(body: dict[str, Any], model: type[M]) -> M:
    """The validated ``model`` instance of an opened body (every model rule)."""
    columns = COLUMNAR.get(model.TYPE)
    if columns is not None and "objects" in body:
        body = {**body, "objects": unpack_columns(body["objects"], columns)}
    try:
        return model.model_validate(body)
    except ValidationError as exc:
        raise _describe(exc, model.TYPE) from None
    except RecursionError:
        raise MalformedMessage(f"{model.TYPE} body is nested too deeply") from None


def decode(data: bytes, model: type[M], max_bytes: int = MAX_MESSAGE_BYTES) -> M:
    """Validated ``model`` instance from wire bytes: ``open_body`` then ``from_body``.

    Any failure raises a :class:`CodecError` subclass.
    """
    return from_body(open_body(data, model, max_bytes), model)
