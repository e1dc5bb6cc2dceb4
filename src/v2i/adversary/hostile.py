"""Hostile inputs for the fuzz command (pure, seeded): every kind of bad message a V2X node meets.

``HostileInputs(rng, t_ns)`` makes ``(kind, payload)`` pairs for one message type; the kinds
(``KINDS``) are the issue's list: random bytes, truncated and bit-flipped messages, wrong
envelope, versions and types, unknown keys, wrong shapes, non-finite and extreme values,
absurd timestamps, over-long predictions, oversized payloads. Floods, replays, fake ids and
forged time replies are made by the live driver (``v2i.adversary.fuzz``) from these and from
genuine traffic. Payloads are bytes; nothing here touches Zenoh or a clock.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from v2i.core.objects import ObjectArray
from v2i.fusion.wire import states_from_objects
from schemas.codec import encode
from schemas.wire_view import pack_view, unpack_view
from schemas.messages import (MAX_TIME_NS, MIN_TIME_NS, SCHEMA_VERSION, EgoPose, LinkControl, ObjectList,
                              ObjectListHeader, PredictedPath, PredictionList, TimeReply, TimeRequest)

MS = 1_000_000
TARGET_TYPES = ("object_list", "prediction_list", "time_request", "time_reply", "ego_pose", "link_control")


class HostileInputs:
    """Hostile payloads around a valid message of each type, at time ``t_ns`` (the receiver's
    clock, roughly), claiming to come from ``rsu_id``."""

    def __init__(self, rng: np.random.Generator, rsu_id: str = "rsu1", vehicle_id: str = "ego", link_id: str = "link1"):
        self.rng, self.rsu_id, self.vehicle_id, self.link_id = rng, rsu_id, vehicle_id, link_id

    # --- valid messages to start from ------------------------------------------------------------
    def valid(self, type_name: str, t_ns: int, n_objects: int = 8, **header) -> bytes:
        """A well-formed message of ``type_name`` (``TARGET_TYPES``) stamped around ``t_ns``."""
        make: dict[str, Callable[[], object]] = {
            "object_list": lambda: ObjectList(header=self._header(t_ns, **header), objects=self._objects(n_objects)),
            "prediction_list": lambda: self._predictions(t_ns, n_objects, **header),
            "time_request": lambda: TimeRequest(obu_id=self.vehicle_id, seq=int(self.rng.integers(1 << 20)), t1_ns=t_ns),
            "time_reply": lambda: TimeReply(rsu_id=self.rsu_id, seq=int(self.rng.integers(1 << 20)), t1_ns=t_ns,
                                            t2_ns=t_ns + 5 * MS, t3_ns=t_ns + 6 * MS),
            "ego_pose": lambda: EgoPose(vehicle_id=self.vehicle_id, t_ns=t_ns, x=float(self.rng.uniform(-50, 50)),
                                        y=float(self.rng.uniform(-50, 50))),
            "link_control": lambda: LinkControl(link_id="not-" + self.link_id, outage=True, duration_s=3600.0),
        }
        return encode(make[type_name]())

    def _header(self, t_ns: int, seq: int | None = None, age_ms: float = 150.0, **fields) -> ObjectListHeader:
        capture = t_ns - round(age_ms * MS)
        return ObjectListHeader(rsu_id=fields.pop("rsu_id", self.rsu_id), capture_time_ns=capture,
                                seq=int(self.rng.integers(1 << 40)) if seq is None else seq,
                                publish_time_ns=fields.pop("publish_time_ns", capture + 100 * MS), **fields)

    def _objects(self, n: int, spread_m: float = 80.0, **columns) -> tuple:
        xy = self.rng.uniform(-spread_m, spread_m, (n, 2))
        objs = ObjectArray(ids=np.arange(n), cls=self.rng.integers(0, 4, n), xy=xy, z=np.zeros(n),
                           lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=self.rng.uniform(-3, 3, n),
                           vxy=self.rng.uniform(-20, 20, (n, 2)), cov_xy=np.tile(np.eye(2), (n, 1, 1)))
        return states_from_objects(objs.with_(**columns) if columns else objs)

    def _predictions(self, t_ns: int, n: int, points: int = 50, **header) -> PredictionList:
        objects = self._objects(n)
        paths = tuple(PredictedPath(id=o.id, x=[o.x] * points, y=[o.y] * points, yaw=[0.0] * points) for o in objects)
        return PredictionList(header=self._header(t_ns, **header), objects=objects, paths=paths)

    # --- the hostile kinds -------------------------------------------------------------------------
    def make(self, kind: str, type_name: str, t_ns: int) -> bytes:
        """One hostile payload of ``kind`` (``KINDS``) built around a ``type_name`` message."""
        return KINDS[kind](self, type_name, t_ns)

    def random_bytes(self, type_name: str, t_ns: int) -> bytes:
        return self.rng.bytes(int(self.rng.integers(0, 4096)))

    def truncated(self, type_name: str, t_ns: int) -> bytes:
        data = self.valid(type_name, t_ns)
        return data[: int(self.rng.integers(0, len(data)))]

    def bit_flips(self, type_name: str, t_ns: int) -> bytes:
        data = bytearray(self.valid(type_name, t_ns))
        for i in self.rng.integers(0, len(data), int(self.rng.integers(1, 8))):
            data[i] ^= 1 << int(self.rng.integers(8))
        return bytes(data)

    def wrong_envelope(self, type_name: str, t_ns: int) -> bytes:
        envelope = self._unpacked(type_name, t_ns)
        choice = int(self.rng.integers(6))
        if choice == 0:
            envelope["v"] = int(self.rng.choice([0, 1, SCHEMA_VERSION + 1, -1, 2**40]))
        elif choice == 1:
            envelope["t"] = str(self.rng.choice(["object_list", "fused_object_list", "time_reply", "x" * 500]))
        elif choice == 2:
            envelope["extra"] = 1
        elif choice == 3:
            del envelope["d"]
        elif choice == 4:
            envelope = [envelope["v"], envelope["t"], envelope["d"]]
        else:
            envelope["v"] = "2"
        return pack_view(envelope)

    def unknown_keys(self, type_name: str, t_ns: int) -> bytes:
        envelope = self._unpacked(type_name, t_ns)
        target = envelope["d"].get("header", envelope["d"]) if self.rng.random() < 0.5 else envelope["d"]
        target[str(self.rng.choice(["evil", "__class__", "x" * 100, "schema_version_2"]))] = 1
        if isinstance(envelope["d"].get("objects"), dict) and self.rng.random() < 0.5:
            envelope["d"]["objects"]["evil"] = b"\x00" * 8
        return pack_view(envelope)

    def header_version(self, type_name: str, t_ns: int) -> bytes:
        envelope = self._unpacked("object_list" if type_name not in ("object_list", "prediction_list") else type_name,
                                  t_ns)
        envelope["d"]["header"]["schema_version"] = int(self.rng.choice([0, 1, SCHEMA_VERSION - 1, SCHEMA_VERSION + 1]))
        return pack_view(envelope)

    def wrong_shapes(self, type_name: str, t_ns: int) -> bytes:
        envelope = self._unpacked(type_name, t_ns)
        body = envelope["d"]
        objects = body.get("objects")
        choice = int(self.rng.integers(7))
        if choice == 0 and isinstance(objects, dict):
            objects["n"] = int(self.rng.choice([-1, objects["n"] + 1, 10**9, 2**63 - 1]))
        elif choice == 1 and isinstance(objects, dict):
            objects["rows"] = objects["rows"][:-1]
        elif choice == 2 and isinstance(objects, dict):
            objects["refs"] = [1, 2, 3]
        elif choice == 3:
            body["header" if "header" in body else next(iter(body))] = [1, "a", None]
        elif choice == 4:
            nested: object = 0
            for _ in range(int(self.rng.integers(50, 5000))):
                nested = [nested]
            body[next(iter(body))] = nested
        elif choice == 5:
            body[next(iter(body))] = "x" * int(self.rng.integers(0, 100_000))
        else:
            body.clear()
        try:
            return pack_view(envelope)
        except (ValueError, OverflowError):  # nesting deeper than msgpack packs: random bytes instead
            return self.random_bytes(type_name, t_ns)

    def non_finite(self, type_name: str, t_ns: int) -> bytes:
        envelope = self._unpacked(type_name, t_ns)
        body = envelope["d"].get("header", envelope["d"])
        key = str(self.rng.choice(sorted(body)))
        body[key] = float(self.rng.choice([np.nan, np.inf, -np.inf]))
        return pack_view(envelope)

    def extreme_values(self, type_name: str, t_ns: int) -> bytes:
        """Valid messages at the edges of every range: what passes validation must not crash."""
        if type_name == "object_list":
            n = int(self.rng.choice([1, 256, 1024]))
            objects = self._objects(n, spread_m=1e6, vxy=self.rng.choice([-200.0, 200.0], (n, 2)),
                                    lwh=np.full((n, 3), 100.0), cov_xy=np.tile(np.eye(2) * 1e4, (n, 1, 1)),
                                    ids=np.full(n, 2**32 - 1), yaw=np.full(n, 99.0))
            return encode(ObjectList(header=self._header(t_ns, age_ms=0.0), objects=objects))
        if type_name == "prediction_list":
            return encode(self._predictions(t_ns, int(self.rng.choice([1, 64])), points=128))
        if type_name == "ego_pose":
            return encode(EgoPose(vehicle_id=self.vehicle_id, t_ns=t_ns, x=float(self.rng.choice([-1e6, 1e6])),
                                  y=float(self.rng.choice([-1e6, 1e6])), vx=200.0, vy=-200.0))
        if type_name == "link_control":
            return encode(LinkControl(link_id=self.link_id, profile="no-such-profile"))
        return self.valid(type_name, t_ns)

    def absurd_times(self, type_name: str, t_ns: int) -> bytes:
        """Stamps far in the past or future, publish before capture, long predictions."""
        if type_name not in ("object_list", "prediction_list"):
            envelope = self._unpacked(type_name, t_ns)
            for key in [k for k in envelope["d"] if k.endswith("_ns")]:
                envelope["d"][key] = int(self.rng.choice([0, -1, MIN_TIME_NS - 1, MAX_TIME_NS + 1, 2**63 - 1]))
            return pack_view(envelope)
        choice = int(self.rng.integers(5))
        header = [dict(age_ms=-900.0), dict(age_ms=3_600_000.0), dict(prediction_ns=10_000 * MS),
                  dict(age_ms=(t_ns - MIN_TIME_NS) // MS), dict(age_ms=-5_000.0)][choice]
        if type_name == "prediction_list":
            return encode(self._predictions(t_ns, 4, **header))
        return encode(ObjectList(header=self._header(t_ns, **header), objects=self._objects(4)))

    def oversized(self, type_name: str, t_ns: int) -> bytes:
        if self.rng.random() < 0.5:
            return self.rng.bytes(int(self.rng.integers(1 << 16, 3 << 20)))
        return encode(ObjectList(header=self._header(t_ns, sensor="s" * 128), objects=self._objects(1024)))

    def large_malformed(self, type_name: str, t_ns: int) -> bytes:
        """A 1024-object list whose packed rows are one byte short: all the cost of a big
        message, none of its validity."""
        envelope = unpack_view(encode(ObjectList(header=self._header(t_ns), objects=self._objects(1024))))
        envelope["d"]["objects"]["rows"] = envelope["d"]["objects"]["rows"][:-1]
        return pack_view(envelope)

    def _unpacked(self, type_name: str, t_ns: int) -> dict:
        return unpack_view(self.valid(type_name, t_ns))


KINDS: dict[str, Callable[[HostileInputs, str, int], bytes]] = {
    "random_bytes": HostileInputs.random_bytes,
    "truncated": HostileInputs.truncated,
    "bit_flips": HostileInputs.bit_flips,
    "wrong_envelope": HostileInputs.wrong_envelope,
    "header_version": HostileInputs.header_version,
    "unknown_keys": HostileInputs.unknown_keys,
    "wrong_shapes": HostileInputs.wrong_shapes,
    "non_finite": HostileInputs.non_finite,
    "extreme_values": HostileInputs.extreme_values,
    "absurd_times": HostileInputs.absurd_times,
    "oversized": HostileInputs.oversized,
    "large_malformed": HostileInputs.large_malformed,
}
