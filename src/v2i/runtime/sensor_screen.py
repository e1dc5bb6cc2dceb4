"""Checks on a node's sensor inputs (``schemas.sensor_messages``) before its pipeline sees them.

Pure: the receive time is an argument. One ``SensorScreen`` per node: it decodes each payload
(every codec rule: size, msgpack, envelope, version, type, unknown keys, NaN, ranges) and then
refuses, each with a counter label (``InputRefused.reason``, all prefixed ``input_``):

- ``input_<codec reason>``: the bytes are not a valid message (``input_malformed``, ...);
- ``input_too_many_objects``: more than ``max_objects`` declared (checked before decoding them);
- ``input_wrong_sensor``: the message names another node than the one whose key it came on;
- ``input_wrong_frame``: RSU detections not in ``map``, vehicle detections not in ``base_link``;
- ``input_future``: stamped (capture, ready or pose time) more than ``future_ms`` after receipt;
- ``input_stale``: captured more than ``max_age_ms`` before receipt;
- ``input_out_of_order``: not newer than the last accepted message of its stream (a duplicate,
  a replay, a reordering).

Stamps are in the publisher's clock, which must be the receiving node's (same host or PTP).
"""

from __future__ import annotations

from dataclasses import dataclass

from schemas.codec import MAX_MESSAGE_BYTES, CodecError, from_body, object_count, open_body
from schemas.sensor_messages import LocalizationPose, SensorObjects

MS = 1_000_000


class InputRefused(CodecError):
    """A sensor input that is refused; ``reason`` is its counter label."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class SensorLimits:
    max_objects: int = 256
    max_age_ms: float = 1000.0
    future_ms: float = 20.0
    max_bytes: int = MAX_MESSAGE_BYTES


class SensorScreen:
    """Decodes and checks the sensor inputs of node ``node_id`` whose detections are in ``frame_id``."""

    def __init__(self, node_id: str, frame_id: str, limits: SensorLimits = SensorLimits()):
        self.node_id, self.frame_id, self.limits = node_id, frame_id, limits
        self._last_ns: dict[str, int] = {}  # stream ("objects", "pose") -> newest accepted time

    def objects(self, payload: bytes, receive_ns: int) -> SensorObjects:
        """The detections of one valid frame; InputRefused otherwise."""
        try:
            body = open_body(payload, SensorObjects, self.limits.max_bytes)
            n = object_count(body)
            if n > self.limits.max_objects:
                raise InputRefused("input_too_many_objects", f"{n} objects, at most {self.limits.max_objects}")
            msg = from_body(body, SensorObjects)
        except InputRefused:
            raise
        except CodecError as exc:
            raise InputRefused(f"input_{exc.reason}", str(exc)) from None
        h = msg.header
        self._check_id(h.sensor_id)
        if h.frame_id != self.frame_id:
            raise InputRefused("input_wrong_frame", f"detections in {h.frame_id!r}, this node takes {self.frame_id!r}")
        self._check_times("objects", h.capture_time_ns, h.ready_time_ns, receive_ns)
        return msg

    def pose(self, payload: bytes, receive_ns: int) -> LocalizationPose:
        """One valid pose estimate; InputRefused otherwise."""
        try:
            msg = from_body(open_body(payload, LocalizationPose, self.limits.max_bytes), LocalizationPose)
        except CodecError as exc:
            raise InputRefused(f"input_{exc.reason}", str(exc)) from None
        self._check_id(msg.vehicle_id)
        self._check_times("pose", msg.t_ns, msg.t_ns, receive_ns)
        return msg

    def _check_id(self, sensor_id: str) -> None:
        if sensor_id != self.node_id:
            raise InputRefused("input_wrong_sensor", f"input of {sensor_id!r} on the key of {self.node_id!r}")

    def _check_times(self, stream: str, capture_ns: int, ready_ns: int, receive_ns: int) -> None:
        """future: t > receive + tolerance; stale: receive - capture > max age; out of order:
        capture <= the newest accepted of the stream. Accepted: the stream's newest is capture."""
        future_ns, max_age_ns = round(self.limits.future_ms * MS), round(self.limits.max_age_ms * MS)
        ahead_ns = max(capture_ns, ready_ns) - receive_ns
        if ahead_ns > future_ns:
            raise InputRefused("input_future", f"{stream} stamped {ahead_ns / MS:.1f} ms after its receipt")
        if receive_ns - capture_ns > max_age_ns:
            raise InputRefused("input_stale", f"{stream} captured {(receive_ns - capture_ns) / MS:.0f} ms "
                                              f"before its receipt, at most {self.limits.max_age_ms:g} ms")
        last_ns = self._last_ns.get(stream)
        if last_ns is not None and capture_ns <= last_ns:
            raise InputRefused("input_out_of_order", f"{stream} captured {(last_ns - capture_ns) / MS:.1f} ms "
                                                     f"before the newest accepted one")
        self._last_ns[stream] = capture_ns
