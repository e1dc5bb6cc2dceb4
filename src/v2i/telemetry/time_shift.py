"""Moving a recording in time (pure): shifted message stamps and the recorded RSU clock.

A replay runs ``shift_ns`` after the recording (``shift_ns`` = new start - recorded start, a
whole number of milliseconds: a CPM / SDSM stamps in ms, so such a shift re-encodes exactly).
Every timestamp a message carries moves by ``shift_ns``: the fields typed ``TimeNs`` in
``schemas.messages`` (``capture_time_ns``, ``publish_time_ns``, ``t_ns``, ...; durations such as
``prediction_ns`` are other types and stay), found from the model, so new stamps move too.
Every clock is moved by the same ``shift_ns``, whatever its offset: a pure translation in time,
so a message's age on arrival and the RSU's offset and drift against the receiver are kept.

The RSU clock in the replay: the recording holds four-timestamp exchanges with the RSU
(t1, t4 host clock; t2, t3 RSU clock). Each gives the offset at host time h = (t1 + t4) / 2,
theta = ((t2 - t1) + (t3 - t4)) / 2 (NTP; error <= half the path asymmetry), and the round-trip
delay d = (t4 - t1) - (t3 - t2). ``RsuClockTrack`` keeps the low-delay exchanges, takes a running
median of their offsets (the jitter of single exchanges goes, a step's edge stays) and
interpolates theta(h) between them (a drift is followed piecewise). The replayed RSU clock at
replay host time t is rsu(t) = t + theta(t - shift_ns). An exchange is ``clock_sync.SyncSample``.
"""

from __future__ import annotations

from functools import cache

import annotated_types
import numpy as np
from scipy.ndimage import median_filter

from v2i.clock.clock_sync import SyncSample
from schemas import list_wire
from schemas.codec import decode, encode
from schemas.messages import MAX_TIME_NS, MIN_TIME_NS, Message, ObjectList

SHIFT_STEP_NS = 1_000_000  # shifts are whole milliseconds (CPM / SDSM time resolution)
DELAY_KEEP_FACTOR = 2.0  # exchanges with a round trip over 2 x the median (+ slack) are not used
DELAY_SLACK_NS = 500_000
MEDIAN_EXCHANGES = 9  # theta(h) from the running median of this many exchanges (~0.9 s at 10 Hz)


def round_shift_ns(shift_ns: int) -> int:
    """``shift_ns`` rounded to a whole millisecond."""
    return int(round(shift_ns / SHIFT_STEP_NS)) * SHIFT_STEP_NS


@cache
def _stamp_fields(model: type[Message]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(names of the TimeNs fields of ``model``, names of its nested-Message fields)."""
    stamps, nested = [], []
    for name, info in model.model_fields.items():
        bounds = {(type(m), getattr(m, "ge", getattr(m, "le", None))) for m in info.metadata}
        if info.annotation is int and {(annotated_types.Ge, MIN_TIME_NS), (annotated_types.Le, MAX_TIME_NS)} <= bounds:
            stamps.append(name)
        elif isinstance(info.annotation, type) and issubclass(info.annotation, Message):
            nested.append(name)
    return tuple(stamps), tuple(nested)


def shift_message(msg: Message, shift_ns: int) -> Message:
    """``msg`` with every timestamp (``TimeNs`` field, nested headers included) moved by ``shift_ns``."""
    stamps, nested = _stamp_fields(type(msg))
    update = {name: getattr(msg, name) + shift_ns for name in stamps}
    update.update({name: shift_message(getattr(msg, name), shift_ns) for name in nested
                   if getattr(msg, name) is not None})
    return msg.model_copy(update=update) if update else msg


def shift_payload(kind: str, model: type[Message] | None, payload: bytes, shift_ns: int,
                  rsu_id: str | None = None) -> bytes:
    """Wire bytes of a recorded payload with its stamps moved by ``shift_ns``: a v2i message
    (``model``) decoded and encoded by ``schemas.codec``; a CPM / SDSM (``kind``) through
    ``schemas.list_wire``. CodecError when it does not decode; ValueError for a kind that has
    no stamps this module knows (JSON, unknown bytes)."""
    if shift_ns == 0:
        return payload
    if model is not None:
        return encode(shift_message(decode(payload, model), shift_ns))
    if kind == "cpm":  # at the byte level: the reference position and every field stay as sent
        from schemas import cpm

        return cpm.shifted(payload, shift_ns // 1_000_000)
    if kind == "sdsm":
        msg = shift_message(list_wire.decode_list(payload, kind, rsu_id), shift_ns)
        assert isinstance(msg, ObjectList)
        data = list_wire.encode_list(msg, kind)
        if data is None:
            raise ValueError(f"{kind}: the shifted list has no message in this encoding")
        return data
    raise ValueError(f"cannot move the stamps of a {kind!r} payload")


Exchange = SyncSample  # one recorded time exchange: t1, t4 host clock; t2, t3 RSU clock (ns)


class RsuClockTrack:
    """theta(host time) of one RSU from recorded exchanges (see the module docstring).

    ``host_ns``, ``offset_ns``: (K,) int64, sorted by host time, low-delay exchanges only;
    ``used`` / ``dropped``: how many exchanges were kept / left out as slow.
    """

    def __init__(self, exchanges: list[Exchange]):
        valid = [e for e in exchanges if e.t4_ns >= e.t1_ns and e.t3_ns >= e.t2_ns]
        delays = np.array([e.round_trip_ns for e in valid], dtype=np.int64)
        limit = DELAY_KEEP_FACTOR * float(np.median(delays)) + DELAY_SLACK_NS if len(delays) else 0.0
        kept = sorted((e for e in valid if e.round_trip_ns <= limit), key=lambda e: e.midpoint_ns)
        self.host_ns = np.array([e.midpoint_ns for e in kept], dtype=np.int64)
        raw_ns = np.array([e.offset_ns for e in kept], dtype=np.int64)
        # a running median over MEDIAN_EXCHANGES: removes the per-exchange jitter, keeps a step's edge
        self.offset_ns = median_filter(raw_ns, size=MEDIAN_EXCHANGES, mode="nearest") if len(raw_ns) else raw_ns
        self.used, self.dropped = len(kept), len(exchanges) - len(kept)

    def __bool__(self) -> bool:
        return self.used > 0

    def offset_at(self, host_ns: int) -> int:
        """theta at recorded host time ``host_ns``: linear between the neighbouring exchanges, the
        first / last one's before / after them (ValueError without any)."""
        if not self.used:
            raise ValueError("no usable time exchange recorded for this RSU")
        # float64 of host time relative to the first exchange: exact to well below a ns over days
        rel = self.host_ns - self.host_ns[0]
        return int(round(float(np.interp(host_ns - int(self.host_ns[0]), rel, self.offset_ns))))

    def rsu_time_ns(self, replay_host_ns: int, shift_ns: int) -> int:
        """The replayed RSU clock at replay host time t: t + theta(t - shift)."""
        return replay_host_ns + self.offset_at(replay_host_ns - shift_ns)
