"""A named view of wire bytes, for tools that inspect or mutate messages (fuzzers, tests).

``unpack_view(data)`` gives every envelope as ``{"v": version, "t": tag, "d": body}``: for an
object list (``schemas.codec`` array envelope) ``body`` maps field names to values, a nested
header is a map too, and ``body["objects"]`` is ``{"n", "present", "widths", "refs", "scales",
"rows", "tables"}`` (``schemas.object_wire``). ``pack_view`` is its inverse, mutations included: a key no
field has becomes an extra positional entry (the decoder calls that malformed), so a mutated
view is still a faithful hostile message. No validation here.
"""

from __future__ import annotations

from typing import Any

import msgpack

from schemas.codec import LIST_TAGS, _layout
from schemas.messages import FusedObjectList, Message, ObjectList, PredictionList
from schemas.sensor_messages import GroundTruth, SensorObjects

SECTION_KEYS = ("n", "present", "widths", "refs", "scales", "rows", "tables")
_MODELS: dict[int, type[Message]] = {LIST_TAGS[m.TYPE]: m for m in
                                     (ObjectList, FusedObjectList, PredictionList, SensorObjects, GroundTruth)}


def unpack_view(data: bytes) -> Any:
    """The named view of a (trusted, well-formed) payload."""
    value = msgpack.unpackb(data, raw=False)
    if not (isinstance(value, list) and len(value) == 4 and value[1] in _MODELS):
        return value
    version, tag, fields, section = value
    body = _names(fields, _MODELS[tag])
    body["objects"] = dict(zip(SECTION_KEYS, section))
    return {"v": version, "t": tag, "d": body}


def pack_view(envelope: Any) -> bytes:
    """Bytes of a (possibly mutated) view: object lists back to their array envelope."""
    model = _MODELS.get(envelope.get("t")) if isinstance(envelope, dict) and type(envelope.get("t")) is int else None
    if model is None or set(envelope) != {"v", "t", "d"} or not isinstance(envelope["d"], dict):
        return msgpack.packb(envelope, use_bin_type=True)
    body = dict(envelope["d"])
    objects = body.pop("objects", None)
    section = ([objects.get(k) for k in SECTION_KEYS if k in objects]
               + [v for k, v in objects.items() if k not in SECTION_KEYS]) if isinstance(objects, dict) else objects
    return msgpack.packb([envelope["v"], envelope["t"], _values(body, model), section], use_bin_type=True)


def _names(fields: list, model: type[Message]) -> dict[str, Any]:
    out = {}
    for (name, _, nested), value in zip(_layout(model), fields):
        if value is not None:
            out[name] = _names(value, nested) if nested is not None and isinstance(value, list) else value
    return out


def _values(body: dict[str, Any], model: type[Message]) -> list[Any]:
    out = []
    for name, _, nested in _layout(model):
        value = body.pop(name, None)
        out.append(_values(dict(value), nested) if nested is not None and isinstance(value, dict) else value)
    out.extend(body.values())  # unknown keys: extra entries
    while out and out[-1] is None:
        out.pop()
    return out
