"""The encodings an RSU object list can travel in (RSU ``--wire v2i|cpm|sdsm``), each on its own key.

- ``v2i``: the project's msgpack codec (``schemas.codec``) on ``v2x/rsu/{id}/objects``;
- ``cpm``: ETSI collective perception message, UPER (``schemas.cpm``) on ``v2x/rsu/{id}/cpm``;
- ``sdsm``: SAE J3224 sensor data sharing message, UPER (``schemas.sdsm``) on ``v2x/rsu/{id}/sdsm``.

``encode_list`` / ``decode_list`` map an ``ObjectList`` through any of them; a standard message
decodes into the same validated ``ObjectList`` the OBU accepts, at the standard's resolution.
Objects a standard message cannot carry (beyond its position range, or past its object count
limit, farthest from the map origin first) are left out by ``fit_standard``, which says how many.
"""

from __future__ import annotations

from collections import Counter
from typing import Any, Literal

import numpy as np

from schemas import keys
from schemas import standard_wire as sw
from schemas.codec import MAX_MESSAGE_BYTES, decode, encode
from schemas.messages import ObjectList

Wire = Literal["v2i", "cpm", "sdsm"]
WIRES: tuple[str, ...] = ("v2i", "cpm", "sdsm")
STANDARD_WIRES: tuple[str, ...] = ("cpm", "sdsm")  # the standards' encodings (UPER), each on its own key
TOPIC_WIRE = {"objects": "v2i", "cpm": "cpm", "sdsm": "sdsm"}
# the wires whose header seq is no message counter (a CPM has none: schemas.cpm.sequence makes one from
# its time), by the header's ``sensor``: a receiver measures no loss from their gaps
UNCOUNTED_SENSORS = frozenset({"cpm"})


def _module(wire: str):
    if wire == "cpm":
        from schemas import cpm

        return cpm
    if wire == "sdsm":
        from schemas import sdsm

        return sdsm
    raise ValueError(f"unknown wire {wire!r}; one of {', '.join(WIRES)}")


def list_key(wire: str, rsu_id: str) -> str:
    """The key an RSU publishes its object lists on in encoding ``wire``."""
    return {"v2i": keys.rsu_objects, "cpm": keys.rsu_cpm, "sdsm": keys.rsu_sdsm}[wire](rsu_id)


def fit_standard(objects: Any, wire: str) -> tuple[dict[str, np.ndarray], Counter[str]]:
    """Object columns of ``objects`` without those standard ``wire`` cannot carry, and how many
    were left out, by reason (``out_of_range``, ``truncated``: the farthest from the map origin)."""
    mod = _module(wire)
    cols = sw.columns_of(objects)
    inside = np.maximum.reduce([np.abs(cols["x"]), np.abs(cols["y"]), np.abs(cols["z"])]) <= mod.POSITION_RANGE_M
    counts = Counter(out_of_range=int((~inside).sum()))
    keep = np.flatnonzero(inside)
    if len(keep) > mod.MAX_OBJECTS:
        counts["truncated"] = len(keep) - mod.MAX_OBJECTS
        order = np.argsort(np.hypot(cols["x"][keep], cols["y"][keep]), kind="stable")[: mod.MAX_OBJECTS]
        keep = np.sort(keep[order])
    if len(keep) < len(inside):
        cols = {k: v[keep] for k, v in cols.items()}
    return cols, +counts


Origin = tuple[float, float]  # a site's WGS84 origin: latitude, longitude (degrees)


def _origin_kw(wire: str, origin: Origin | None) -> dict[str, Any]:
    """The origin keyword of a standard codec (the CPM takes degrees, the SDSM 0.1 microdegrees)."""
    if origin is None:
        return {}
    if wire == "cpm":
        return {"origin": origin}
    return {"origin_e7": (int(round(origin[0] * 1e7)), int(round(origin[1] * 1e7)))}


def encode_list(msg: ObjectList, wire: str, origin: Origin | None = None) -> bytes | None:
    """Wire bytes of an RSU object list in encoding ``wire`` (standard: after ``fit_standard``);
    None where the encoding has no message for it (an SDSM carries at least one object).
    ``origin``: the site's WGS84 origin (the ``map`` frame's), a standard message's reference
    position (None: 0 N 0 E)."""
    if wire == "v2i":
        return encode(msg)
    cols = fit_standard(msg.objects, wire)[0]
    if wire == "sdsm" and not len(cols["id"]):
        return None
    return _module(wire).encode(msg.header, cols, **_origin_kw(wire, origin))


def prepare(wire: str) -> None:
    """Compile ``wire``'s ASN.1 now (a publisher does it before its first message)."""
    if wire != "v2i":
        sw.compiled(_module(wire).ASN1_FILE)


def decode_list(data: bytes, wire: str, rsu_id: str | None = None, max_bytes: int = MAX_MESSAGE_BYTES,
                origin: Origin | None = None) -> ObjectList:
    """The validated ObjectList of wire bytes in encoding ``wire``; ``rsu_id``: the RSU of the key
    it came on (a standard message names its station by number); ``origin``: the receiver's site
    origin (a standard message is placed in its ``map``; None: about the message's own reference
    position). Every failure is a CodecError."""
    if wire == "v2i":
        return decode(data, ObjectList, max_bytes)
    header, columns = _module(wire).decode(data, rsu_id, max_bytes=min(max_bytes, sw.MAX_STANDARD_BYTES),
                                           **_origin_kw(wire, origin))
    return sw.object_list(header, columns)
