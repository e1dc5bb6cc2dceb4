"""What a recorded Zenoh sample is, and what goes into MCAP for it (pure: no I/O, no clock).

Every sample is recorded raw, as it was on the wire, on a channel named after its key
expression; its *kind* says how to read it back:

==============  =========================  ==================  ====================================
kind            message_encoding           schema encoding     schema data
==============  =========================  ==================  ====================================
v2i type name   ``v2i-msgpack``            ``jsonschema``      the pydantic JSON schema of the
(object_list,                                                  *decoded* model (``model_json_schema``)
obu_metrics..)
``cpm``         ``uper``                   ``asn1``            ``schemas/asn1/V2I-CPM.asn``
``sdsm``        ``uper``                   ``asn1``            ``schemas/asn1/V2I-SDSM.asn``
``json``        ``json``                   (none)              self-describing (link stats)
``unknown``     ``application/octet-stream`` (none)            anything else, kept byte for byte
==============  =========================  ==================  ====================================

Signed messages (an RSU run with ``--pki``: ``v2i.security.envelope``) are recorded as they were
on the wire, envelope and signature included (that is the evidence); their kind is that of the
payload inside, ``Kind.signed`` is set and the channel's message encoding is ``v2i-signed+``
followed by the payload's (e.g. ``v2i-signed+v2i-msgpack``): the schema describes the payload,
``v2i.security.envelope.unwrap`` gives it. Readers (derived channels, time exchanges, ``v2i replay``)
unwrap without checking the signature: the recording is evidence, not a trust decision.

Honest note on ``v2i-msgpack``: the bytes are the project's codec envelope (``schemas.codec``:
positional fields, bit-packed quantised object columns), *not* a msgpack map that the JSON
schema describes field by field; the schema describes what ``schemas.codec.decode(data,
Model)`` returns. No generic tool decodes these channels; the derived channels below are for
the tools.

Derived channels (JSON, so that Foxglove opens them): object lists become
``foxglove.SceneUpdate`` messages (one cube entity per object, in the ``map`` frame; fused
lists are moved from ``base_link`` with the ego pose they carry); every other v2i message
becomes its plain JSON (``model_dump(mode="json")``), so the Plot panel can plot e.g.
``/vehicle/v2x/obu/ego/metrics/json.output_deadline_misses``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import cache
from importlib import resources

import msgpack
import numpy as np
from pydantic.json_schema import GenerateJsonSchema

from v2i.core.frames import Pose2D, base_to_map_points
from schemas import image_messages, messages, sensor_messages  # noqa: F401 (register every Message type)
from schemas.codec import LIST_TAGS, MAX_CONTAINER_LEN
from schemas.list_wire import STANDARD_WIRES  # key suffix -> UPER message of that standard
from schemas.messages import FusedObjectList, Message, ObjectList
from v2i.security.envelope import unwrap

V2I_ENCODING = "v2i-msgpack"
SIGNED_ENCODING = "v2i-signed+"  # prefix of a signed channel's message encoding (+ the payload's)
UNKNOWN = "unknown"
SCENE_SCHEMA = "foxglove.SceneUpdate"
# RGBA per source: RSU lists orange; fused objects blue when the RSU contributed, grey when own LiDAR only
RSU_COLOR = {"r": 1.0, "g": 0.55, "b": 0.0, "a": 0.6}
FUSED_RSU_COLOR = {"r": 0.1, "g": 0.45, "b": 1.0, "a": 0.6}
FUSED_OWN_COLOR = {"r": 0.6, "g": 0.6, "b": 0.6, "a": 0.6}
ENTITY_LIFETIME_NS = 300_000_000  # an entity not replaced within 3 cycles disappears


@dataclass(frozen=True)
class Kind:
    """How a recorded payload is read back: ``name`` (a v2i TYPE, a wire, json, unknown),
    the MCAP message encoding, the model that decodes it (v2i kinds only), and whether the bytes
    are a signed envelope around such a payload (``signed``; then ``name`` and ``model`` are the
    payload's)."""

    name: str
    message_encoding: str
    model: type[Message] | None = None
    signed: bool = False

    @property
    def label(self) -> str:
        """``name``, or ``signed-<name>``: what tells two channels on one key apart."""
        return f"signed-{self.name}" if self.signed else self.name


def _all_subclasses(cls: type) -> list[type]:
    out = []
    for sub in cls.__subclasses__():
        out += [sub, *_all_subclasses(sub)]
    return out


@cache
def models_by_type() -> dict[str, type[Message]]:
    """Every wire message model by its ``TYPE`` (the map envelope's ``t``): the models of the
    ``schemas`` package only (other code may subclass Message with the same TYPE, e.g. a test's
    legacy codec), each TYPE's first definition."""
    out: dict[str, type[Message]] = {}
    for m in _all_subclasses(Message):
        if m.__module__.startswith("schemas.") and "TYPE" in vars(m):
            out.setdefault(m.TYPE, m)
    return out


@cache
def _list_models() -> dict[int, type[Message]]:
    """List envelope tag -> model (``schemas.codec.LIST_TAGS`` inverted)."""
    by_type = models_by_type()
    return {tag: by_type[name] for name, tag in LIST_TAGS.items()}


def v2i_type(payload: bytes) -> type[Message] | None:
    """The v2i model a payload's envelope names (map ``{"v", "t", "d"}`` or list ``[v, tag, ...]``),
    or None when it is not a v2i envelope. Bounded: msgpack containers over the codec's limit fail."""
    try:
        envelope = msgpack.unpackb(payload, raw=False, strict_map_key=False, max_array_len=MAX_CONTAINER_LEN,
                                   max_map_len=MAX_CONTAINER_LEN, max_str_len=len(payload),
                                   max_bin_len=len(payload), max_ext_len=0)
    except Exception:  # noqa: BLE001 - msgpack raises many types on hostile bytes
        return None
    if isinstance(envelope, dict) and isinstance(envelope.get("t"), str):
        return models_by_type().get(envelope["t"])
    if isinstance(envelope, list) and len(envelope) == 4 and isinstance(envelope[1], int):
        return _list_models().get(envelope[1])
    return None


def classify(key: str, payload: bytes) -> Kind:
    """The kind of one sample on ``key`` (see the module table); a signed envelope's is its payload's,
    ``signed`` set and its encoding prefixed with ``SIGNED_ENCODING``."""
    inner = unwrap(payload)
    if len(inner) == len(payload):  # not an envelope (one adds >= 92 B around its payload)
        return _classify_plain(key, payload)
    kind = _classify_plain(key, inner)
    return Kind(kind.name, SIGNED_ENCODING + kind.message_encoding, kind.model, signed=True)


def _classify_plain(key: str, payload: bytes) -> Kind:
    topic = key.rsplit("/", 1)[-1]
    if key.startswith("v2x/rsu/") and topic in STANDARD_WIRES:
        return Kind(topic, "uper")
    model = v2i_type(payload)
    if model is not None:
        return Kind(model.TYPE, V2I_ENCODING, model)
    if payload[:1] in (b"{", b"["):
        try:
            json.loads(payload)
            return Kind("json", "json")
        except ValueError:
            pass
    return Kind(UNKNOWN, "application/octet-stream")


def schema_of(kind: Kind) -> tuple[str, str, bytes] | None:
    """(schema name, schema encoding, schema data) of a raw channel; None: no schema (self-describing
    JSON, unknown bytes)."""
    if kind.model is not None:
        return f"v2i.{kind.model.__name__}", "jsonschema", _model_schema(kind.model)
    if kind.name in STANDARD_WIRES:
        filename = f"V2I-{kind.name.upper()}.asn"
        return f"v2i.{kind.name.upper()}", "asn1", resources.files("schemas").joinpath("asn1", filename).read_bytes()
    return None


class _SchemaGenerator(GenerateJsonSchema):
    """Pydantic's JSON schema generator; a field it cannot describe (the object columns' plain
    validator) becomes ``{}`` and is described by ``model_schema``."""

    def handle_invalid_for_json_schema(self, schema, error_info):  # noqa: ARG002
        return {}


@cache
def model_schema(model: type[Message]) -> dict:
    """JSON schema of what ``model_dump(mode="json")`` gives: an ``objects`` field (columns on the
    wire) is an array of ``ObjectState`` / ``FusedObject`` dicts."""
    schema = model.model_json_schema(mode="serialization", schema_generator=_SchemaGenerator)
    info = model.model_fields.get("objects")
    if info is not None:
        item = (messages.FusedObject if model is FusedObjectList else messages.ObjectState).model_json_schema(mode="serialization")
        schema.setdefault("$defs", {}).update(item.pop("$defs", {}))
        schema["properties"]["objects"] = {"type": "array", "items": item}
    return schema


@cache
def _model_schema(model: type[Message]) -> bytes:
    schema = dict(model_schema(model))
    schema["description"] = (f"{schema.get('description', '')} Wire bytes: schemas.codec envelope (v2i-msgpack); "
                             f"this schema describes schemas.codec.decode(data, {model.__name__}).").strip()
    return json.dumps(schema).encode()


# ------------------------------------------------------------------ derived (Foxglove) messages


def derived_topic(topic: str, msg: Message) -> str:
    """Topic of the derived channel of a raw channel: ``<topic>/scene`` or ``<topic>/json``."""
    return f"{topic}/scene" if isinstance(msg, (ObjectList, FusedObjectList)) else f"{topic}/json"


def derived_message(msg: Message, log_time_ns: int) -> tuple[str, dict]:
    """(schema name, JSON object) derived from a decoded message: a ``foxglove.SceneUpdate`` for an
    object list, else ``("v2i.<Model>", model_dump)``."""
    if isinstance(msg, ObjectList):
        return SCENE_SCHEMA, scene_update(_map_boxes_rsu(msg), f"rsu-{msg.header.rsu_id}", log_time_ns)
    if isinstance(msg, FusedObjectList):
        return SCENE_SCHEMA, scene_update(_map_boxes_fused(msg), f"obu-{msg.vehicle_id}", log_time_ns)
    return f"v2i.{type(msg).__name__}", msg.model_dump(mode="json")


def _map_boxes_rsu(msg: ObjectList) -> dict[str, np.ndarray]:
    """Columns (N,) of an RSU list's boxes in ``map``: id, x, y, yaw, length, width, height, colour index."""
    o = msg.objects
    return {"id": o.ids, "x": o.column("x"), "y": o.column("y"), "z": o.column("z"), "yaw": o.column("yaw"),
            "length": o.column("length"), "width": o.column("width"), "height": o.column("height"),
            "rsu": np.ones(len(o), dtype=bool)}


def _map_boxes_fused(msg: FusedObjectList) -> dict[str, np.ndarray]:
    """A fused list's boxes moved from ``base_link`` to ``map``: p_map = R(ego_yaw) p_base + ego_xy,
    yaw_map = yaw + ego_yaw."""
    o = msg.objects
    ego = Pose2D(msg.ego_x, msg.ego_y, msg.ego_yaw)
    xy = base_to_map_points(np.column_stack([o.column("x"), o.column("y")]).reshape(-1, 2), ego)
    return {"id": o.ids, "x": xy[:, 0], "y": xy[:, 1], "z": o.column("z"), "yaw": o.column("yaw") + msg.ego_yaw,
            "length": o.column("length"), "width": o.column("width"), "height": o.column("height"),
            "rsu": (o.column("sources").astype(np.int64) & messages.SOURCE_RSU) != 0}


def scene_update(boxes: dict[str, np.ndarray], prefix: str, t_ns: int) -> dict:
    """A ``foxglove.SceneUpdate`` (JSON) replacing one cube entity per box, ids ``<prefix>-<id>``.
    The box centre is lifted by half its height (v2i ``z`` is the ground contact height);
    orientation q = (0, 0, sin(yaw/2), cos(yaw/2)) about +z."""
    stamp = {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}
    lifetime = {"sec": 0, "nsec": ENTITY_LIFETIME_NS}
    entities = []
    for i in range(len(boxes["id"])):
        half_yaw = 0.5 * float(boxes["yaw"][i])
        color = (RSU_COLOR if prefix.startswith("rsu") else FUSED_RSU_COLOR) if boxes["rsu"][i] else FUSED_OWN_COLOR
        cube = {"pose": {"position": {"x": float(boxes["x"][i]), "y": float(boxes["y"][i]),
                                      "z": float(boxes["z"][i]) + 0.5 * float(boxes["height"][i])},
                         "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(half_yaw), "w": math.cos(half_yaw)}},
                "size": {"x": float(boxes["length"][i]), "y": float(boxes["width"][i]), "z": float(boxes["height"][i])},
                "color": color}
        entities.append({"timestamp": stamp, "frame_id": "map", "id": f"{prefix}-{int(boxes['id'][i])}",
                         "lifetime": lifetime, "frame_locked": False, "metadata": [], "cubes": [cube],
                         "arrows": [], "spheres": [], "cylinders": [], "lines": [], "triangles": [], "texts": [],
                         "models": []})
    return {"deletions": [], "entities": entities}


def _obj(properties: dict, description: str = "") -> dict:
    return {"type": "object", "description": description, "properties": properties}


_NUM = {"type": "number"}
_TIME = _obj({"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}})
_VEC3 = _obj({"x": _NUM, "y": _NUM, "z": _NUM})
_COLOR = _obj({"r": _NUM, "g": _NUM, "b": _NUM, "a": _NUM})
_POSE = _obj({"position": _VEC3, "orientation": _obj({"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM})})
_CUBE = _obj({"pose": _POSE, "size": _VEC3, "color": _COLOR}, "A primitive representing a cube or rectangular prism")
_ANY_LIST = {"type": "array", "items": {"type": "object"}}
# Foxglove's foxglove.SceneUpdate JSON schema, the parts v2i writes (other primitive lists are empty arrays)
SCENE_UPDATE_SCHEMA = json.dumps({
    "title": SCENE_SCHEMA, "description": "An update to the entities displayed in a 3D scene", "type": "object",
    "properties": {
        "deletions": {"type": "array", "items": _obj({"timestamp": _TIME, "type": {"type": "integer"},
                                                       "id": {"type": "string"}})},
        "entities": {"type": "array", "items": _obj({
            "timestamp": _TIME, "frame_id": {"type": "string"}, "id": {"type": "string"}, "lifetime": _TIME,
            "frame_locked": {"type": "boolean"},
            "metadata": {"type": "array", "items": _obj({"key": {"type": "string"}, "value": {"type": "string"}})},
            "cubes": {"type": "array", "items": _CUBE},
            **{name: _ANY_LIST for name in ("arrows", "spheres", "cylinders", "lines", "triangles", "texts",
                                            "models")}}, "A visual element in a 3D scene")},
    },
}).encode()


def derived_schema(name: str, model: type[Message] | None) -> bytes:
    """JSON schema of a derived channel: Foxglove's SceneUpdate, or the model's own."""
    if name == SCENE_SCHEMA:
        return SCENE_UPDATE_SCHEMA
    return json.dumps(model_schema(model)).encode()
