"""The one wire codec: versioned msgpack envelopes, validated decode.

Two envelope shapes, both msgpack:

- object lists (``ObjectList``, ``FusedObjectList``, ``PredictionList``, ``SensorObjects``,
  ``GroundTruth``: the models with an ``objects`` field) are one array
  ``[SCHEMA_VERSION, tag, fields, objects]``: ``tag`` a small int (``LIST_TAGS``), ``fields`` the
  model's other fields in declaration order (a nested header likewise), ``nil`` where a field has
  its default and trailing ``nil`` left out, ``objects`` the column section of
  :mod:`schemas.object_wire` (per-message column widths, bit-packed rows);
- every other message is ``{"v": SCHEMA_VERSION, "t": Model.TYPE, "d": model_dump()}``.

Object values are quantisation codes: the columns hold grid values ``k * step`` and decoding
computes ``k * step`` again, so ``decode(encode(m)) == m`` exactly. Every failure of
:func:`decode` on untrusted bytes is a :class:`CodecError` whose ``reason`` is a short label fit
for a rejection counter.
"""

from __future__ import annotations

import reprlib
from collections.abc import Callable
from functools import cache
from typing import Any, TypeVar

import msgpack
from pydantic import PlainSerializer, ValidationError, WrapSerializer

from schemas.columns import OBJECT_SPECS, ObjectColumns
from schemas.errors import (CodecError, InvalidMessage, MalformedMessage, MessageTooLarge,  # noqa: F401 (re-exported)
                     SchemaVersionError, WrongMessageType)
from schemas.messages import (SCHEMA_VERSION, FusedObjectList, Message, ObjectList, ObjectListHeader, PredictedPath,
                       PredictionList)
from schemas.object_wire import EMPTY_SECTION, unpack_objects, wire_section
from schemas.object_wire import object_count as _section_count
from schemas.sensor_messages import GroundTruth, SensorObjects

MAX_MESSAGE_BYTES = 1 << 20
# Largest msgpack array/map accepted. The unpacker pre-allocates a container from its
# declared length, so this bounds the memory a tiny hostile payload can claim.
MAX_CONTAINER_LEN = 4096
ENVELOPE_KEYS = frozenset({"v", "t", "d"})
LIST_ENVELOPE_LEN = 4
# Envelope tag of each object-list model (the array envelope); names of the object columns.
LIST_TAGS: dict[str, int] = {ObjectList.TYPE: 1, FusedObjectList.TYPE: 2, PredictionList.TYPE: 3,
                             SensorObjects.TYPE: 4, GroundTruth.TYPE: 5}
OBJECT_COLUMNS = OBJECT_SPECS  # each has .name: the object attributes in wire order

M = TypeVar("M", bound=Message)

_short = reprlib.Repr()
_short.maxstring = 40
_short.maxother = 40
_short.maxlevel = 2


# ---------------------------------------------------------------- positional fields


@cache
def _layout(model: type[Message]) -> tuple[tuple[str, Any, type[Message] | None], ...]:
    """(name, default, nested model or None) of each field but ``objects``, in declaration order."""
    out = []
    for name, info in model.model_fields.items():
        if name == "objects":
            continue
        nested = info.annotation if isinstance(info.annotation, type) and issubclass(info.annotation, Message) else None
        out.append((name, info.default, nested))
    return tuple(out)


def _positional(msg: Message) -> list[Any]:
    """The fields of ``msg`` (but ``objects``) as a list: nil for a default, trailing nils dropped."""
    out: list[Any] = []
    for name, default, nested in _layout(type(msg)):
        value = getattr(msg, name)
        if value == default and type(value) is type(default):
            out.append(None)
        elif nested is not None:
            out.append(_positional(value))
        elif isinstance(value, tuple):
            out.append([_path_dump(v) if type(v) is PredictedPath else v.model_dump(mode="python")
                        if isinstance(v, Message) else v for v in value])
        else:
            out.append(value)
    while out and out[-1] is None:
        out.pop()
    return out


def _path_dump(path: PredictedPath) -> dict[str, Any]:
    """``path.model_dump(mode="python")`` of a predicted path (plain fields: its id and three tuples
    of floats, in declaration order) without pydantic's serializer, ~4x faster (~40 per prediction list)."""
    return {"id": path.id, "x": path.x, "y": path.y, "yaw": path.yaw}


def _named(values: Any, model: type[Message], where: str) -> dict[str, Any]:
    """The field map of a positional list (inverse of ``_positional``; nil: the default)."""
    layout = _layout(model)
    if not isinstance(values, list) or len(values) > len(layout):
        got = f"{len(values)} entries" if isinstance(values, list) else type(values).__name__
        raise MalformedMessage(f"{where} must be an array of at most {len(layout)} fields, got {got}")
    body = {}
    for (name, _, nested), value in zip(layout, values):
        if value is not None:
            body[name] = _named(value, nested, f"{where}.{name}") if nested is not None and isinstance(value, list) \
                else value
    return body


# ---------------------------------------------------------------- encode


@cache
def _dumps_as_stored(model: type[Message]) -> bool:
    """True when ``model_dump(mode="python")`` of a ``model`` is its field dict as stored (``__dict__``,
    in declaration order): every field a plain int, str, float or bool, none excluded or with a
    serializer, no computed field, no extra keys (a time request or reply; test_codec_fast_paths)."""
    decorators = model.__pydantic_decorators__
    plain = all(f.annotation in (int, str, float, bool) and not f.exclude
                and not any(isinstance(m, (PlainSerializer, WrapSerializer)) for m in f.metadata)
                for f in model.model_fields.values())
    return (plain and model.model_config.get("extra") == "forbid" and not model.model_computed_fields
            and not decorators.field_serializers and not decorators.model_serializers)


def encode(msg: Message, max_bytes: int = MAX_MESSAGE_BYTES) -> bytes:
    """msgpack bytes of ``msg`` in a versioned envelope, at most ``max_bytes`` long.

    Raises InvalidMessage if a value cannot be represented on the wire and
    MessageTooLarge if the result exceeds ``max_bytes``.
    """
    if not isinstance(msg, Message):
        raise TypeError(f"encode() takes a schemas Message, got {type(msg).__name__}")
    tag = LIST_TAGS.get(msg.TYPE)
    if tag is None:
        body = msg.__dict__ if _dumps_as_stored(type(msg)) else msg.model_dump(mode="python")
        envelope: Any = {"v": SCHEMA_VERSION, "t": msg.TYPE, "d": body}
    else:
        envelope = [SCHEMA_VERSION, tag, _positional(msg), wire_section(msg.objects)]  # = pack_objects(msg.objects)
    try:
        data = msgpack.packb(envelope, use_bin_type=True)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InvalidMessage(f"cannot encode {msg.TYPE}: {exc}") from None
    if len(data) > max_bytes:
        raise MessageTooLarge(f"encoded {msg.TYPE} is {len(data)} bytes, limit is {max_bytes}")
    return data


# ---------------------------------------------------------------- decode


def _unpack(data: bytes | bytearray | memoryview, size: int, max_bytes: int) -> Any:
    """One msgpack value from untrusted bytes (at most ``max_bytes``: checked before), with container
    limits: ``msgpack.unpackb`` (~1 us less than an ``Unpacker``); any failure of it (malformed,
    truncated, trailing bytes) is read again by ``_unpack_checked`` for its precise error."""
    try:
        return msgpack.unpackb(data, raw=False, strict_map_key=True, max_array_len=MAX_CONTAINER_LEN,
                               max_map_len=MAX_CONTAINER_LEN, max_ext_len=0)
    except Exception:  # noqa: BLE001 (every failure: the checked reader names it)
        return _unpack_checked(data, size, max_bytes)


def _unpack_checked(data: bytes | bytearray | memoryview, size: int, max_bytes: int) -> Any:
    """One msgpack value from untrusted bytes, with container and buffer limits; MalformedMessage
    saying what is wrong."""
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
    """The body of a checked envelope: shape, then version, then type tag (an object list's
    body: its named fields, ``objects`` still the packed section)."""
    if isinstance(envelope, list) and len(envelope) == LIST_ENVELOPE_LEN:
        version, tag, fields, objects = envelope
    elif isinstance(envelope, dict) and envelope.keys() == ENVELOPE_KEYS:
        version, tag, fields, objects = envelope["v"], envelope["t"], envelope["d"], None
    else:
        got = f"keys {sorted(map(repr, envelope))}" if isinstance(envelope, dict) else type(envelope).__name__
        raise MalformedMessage(f"envelope must be a map with keys 'v', 't', 'd' or a {LIST_ENVELOPE_LEN}-entry "
                               f"object-list array, got {got[:80]}")
    if type(version) is not int:
        raise MalformedMessage(f"envelope version must be an integer, got {_short.repr(version)}")
    if version != SCHEMA_VERSION:
        raise SchemaVersionError(f"schema version {version} received, this build speaks version {SCHEMA_VERSION}")
    if type(tag) not in (str, int):
        raise MalformedMessage(f"envelope type tag must be a string or an integer, got {_short.repr(tag)}")
    if tag != LIST_TAGS.get(model.TYPE, model.TYPE):
        raise WrongMessageType(f"message type {_short.repr(tag)} received where {model.TYPE!r} was expected")
    if objects is None:
        if not isinstance(fields, dict):
            raise MalformedMessage(f"envelope body 'd' must be a map, got {type(fields).__name__}")
        return fields
    return {**_named(fields, model, "fields"), "objects": objects}


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
    if type(data) is bytes:  # (the usual case: its length is its size)
        size = len(data)
    elif isinstance(data, (bytes, bytearray, memoryview)):
        size = memoryview(data).nbytes
    else:
        raise TypeError(f"decode() takes bytes, got {type(data).__name__}")
    if size > max_bytes:
        raise MessageTooLarge(f"{model.TYPE} payload is {size} bytes, limit is {max_bytes}")
    body = _open_envelope(_unpack(data, size, max_bytes), model)
    _check_stated_version(body, model)
    header = body.get("header")
    if isinstance(header, dict):
        _check_stated_version(header, model)
    return body


def _check_stated_version(holder: dict[str, Any], model: type[Message]) -> None:
    """SchemaVersionError when a body or header states an integer schema version not this build's."""
    stated = holder.get("schema_version", SCHEMA_VERSION)
    if type(stated) is int and stated != SCHEMA_VERSION:
        raise SchemaVersionError(f"{model.TYPE} states schema version {stated}, this build speaks "
                                 f"version {SCHEMA_VERSION}")


def header_of(body: dict[str, Any]) -> ObjectListHeader:
    """The validated header of an opened object or prediction list body (cheap: no objects)."""
    try:
        return ObjectListHeader.model_validate(body.get("header"))
    except ValidationError as exc:
        err = _describe(exc, ObjectListHeader.TYPE)
        raise InvalidMessage(f"header: {err}", f"header.{err.field}") from None


def object_count(body: dict[str, Any]) -> int:
    """Objects (and, for predictions, paths) an opened body declares, before any is decoded."""
    count, paths = _section_count(body.get("objects")), body.get("paths")
    return max(count, len(paths)) if isinstance(paths, list) else count


def path_point_count(body: dict[str, Any]) -> int:
    """Predicted positions an opened prediction list carries (its size once decoded), before decoding."""
    paths = body.get("paths")
    if not isinstance(paths, list):
        return 0
    return sum(len(p["x"]) for p in paths if isinstance(p, dict) and isinstance(p.get("x"), list))


def from_body(body: dict[str, Any], model: type[M], unpack: Callable[[Any, bool], ObjectColumns] = unpack_objects) -> M:
    """The validated ``model`` instance of an opened body (every model rule). ``unpack``: the
    objects section's decoder, ``object_wire.unpack_objects`` or one giving its very result."""
    if model.TYPE in LIST_TAGS:
        objects = unpack(body.get("objects", list(EMPTY_SECTION)), model is FusedObjectList)
        body = {**body, "objects": objects}
    try:
        return model.__pydantic_validator__.validate_python(body)  # = model.model_validate(body)
    except ValidationError as exc:
        raise _describe(exc, model.TYPE) from None
    except RecursionError:
        raise MalformedMessage(f"{model.TYPE} body is nested too deeply") from None


def decode(data: bytes, model: type[M], max_bytes: int = MAX_MESSAGE_BYTES,
           unpack: Callable[[Any, bool], ObjectColumns] = unpack_objects) -> M:
    """Validated ``model`` instance from wire bytes: ``open_body`` then ``from_body`` (``unpack``: as there).

    Any failure raises a :class:`CodecError` subclass.
    """
    return from_body(open_body(data, model, max_bytes), model, unpack)
