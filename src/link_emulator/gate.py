"""Bounds on what peers can make the link emulator hold (used by ``relay``).

A Zenoh callback passes the ``Gate`` before it may enqueue work; messages scheduled for
delivery are counted per direction by ``InFlight``. Both refuse beyond their configured
bounds (``LinkConfig``) instead of growing, and the gate counts every refusal by reason.
``VehiclePosition`` decides which ego poses may move the emulated vehicle.
"""

from __future__ import annotations

import math
import threading
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from v2i.runtime.intake import KeyedBuckets, TokenBucket
from schemas.messages import EgoPose
from v2i.core.clock import Clock

from link_emulator.config import LinkConfig


class Gate:
    """What a Zenoh callback must pass before it may enqueue work (thread-safe): a payload of at
    most ``max_message_bytes``, a token of its key's bucket (the least recently used of
    ``max_keys`` buckets is forgotten), its bytes from the bucket of all keys together
    (``total_bytes_per_s``, one second's worth at once), and room among the
    ``max_pending_arrivals`` not yet processed."""

    def __init__(self, config: LinkConfig, clock: Clock, max_keys: int = 1024) -> None:
        self._config, self._clock = config, clock
        self._lock = threading.Lock()
        self._buckets = KeyedBuckets(config.source_rate_hz, config.source_burst, max_keys)
        self._bytes = TokenBucket(config.total_bytes_per_s, round(config.total_bytes_per_s), clock.now_ns())
        self._pending = 0
        self.refused: Counter[str] = Counter()

    def admit(self, key: str, size: int) -> bool:
        """Reserve an arrival slot for one message on ``key``; False (counted) when refused."""
        cfg, now_ns = self._config, self._clock.now_ns()
        with self._lock:
            reason = ("too_large" if size > cfg.max_message_bytes else
                      "rate_limited" if not self._buckets.take(key, now_ns) else
                      "bytes_limited" if not self._bytes.take(now_ns, size) else
                      "overflow" if self._pending >= cfg.max_pending_arrivals else None)
            if reason is not None:
                self.refused[reason] += 1
                return False
            self._pending += 1
            return True

    def done(self) -> None:
        """An admitted arrival has been processed: its slot is free."""
        with self._lock:
            self._pending -= 1

    def count(self, reason: str) -> None:
        with self._lock:
            self.refused[reason] += 1

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self.refused)


@dataclass
class InFlight:
    """Messages of one direction scheduled for delivery and their bytes (scheduler thread only)."""

    messages: int = 0
    bytes: int = 0

    def reserve(self, size: int, config: LinkConfig) -> bool:
        if self.messages >= config.max_in_flight or self.bytes + size > config.max_in_flight_bytes:
            return False
        self.messages, self.bytes = self.messages + 1, self.bytes + size
        return True

    def release(self, size: int) -> None:
        self.messages, self.bytes = self.messages - 1, self.bytes - size


@dataclass
class VehiclePosition:
    """The emulated vehicle's latest plausible ego pose and the RSU distance it implies.

    A relay emulates one vehicle's link. Its poses are those of ``vehicle_id`` (configured,
    or else the first id heard; another id's poses are refused as ``other_vehicle``). A repeat
    of the last pose is a ``duplicate``; a pose no newer than the last one, or implying a speed over ``max_speed_mps`` since it, is refused
    as ``implausible``: a forged pose 1000 km away must not cut the link. Undecodable poses are
    counted in ``rejected``.
    """

    vehicle_id: str | None = None
    max_speed_mps: float = 100.0
    received: int = 0
    rejected: int = 0  # poses that failed to decode, ignored
    refused: Counter = field(default_factory=Counter)  # decodable poses not taken, by reason
    xy_m: tuple[float, float] | None = None  # map frame
    t_ns: int | None = None  # the vehicle's stamp of the pose taken

    def take(self, pose: EgoPose) -> bool:
        """Keep ``pose`` if it is the emulated vehicle's and plausible; False (counted) if not."""
        self.vehicle_id = self.vehicle_id or pose.vehicle_id
        reason = None
        if pose.vehicle_id != self.vehicle_id:
            reason = "other_vehicle"
        elif pose.t_ns == self.t_ns and (pose.x, pose.y) == self.xy_m:
            reason = "duplicate"
        elif self.t_ns is not None:
            dt_s = (pose.t_ns - self.t_ns) * 1e-9
            jump_m = math.hypot(pose.x - self.xy_m[0], pose.y - self.xy_m[1])
            reason = "implausible" if dt_s <= 0 or jump_m > self.max_speed_mps * dt_s else None
        if reason is not None:
            self.refused[reason] += 1
            return False
        self.received += 1
        self.xy_m, self.t_ns = (pose.x, pose.y), pose.t_ns
        return True

    def distance_m(self, rsu_xy_m: tuple[float, float] | None) -> float | None:
        """Vehicle-RSU distance in m, or None while either position is unknown."""
        if rsu_xy_m is None or self.xy_m is None:
            return None
        return math.hypot(self.xy_m[0] - rsu_xy_m[0], self.xy_m[1] - rsu_xy_m[1])

    def as_dict(self, rsu_xy_m: tuple[float, float] | None) -> dict[str, Any]:
        return {"vehicle_id": self.vehicle_id, "received": self.received, "rejected": self.rejected,
                "refused": dict(self.refused), "distance_m": self.distance_m(rsu_xy_m)}
