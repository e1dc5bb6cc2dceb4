"""Bounds on what peers can make the link emulator hold (used by ``relay``).

A Zenoh callback passes the ``Gate`` before it may enqueue work; messages scheduled for
delivery are counted per direction by ``InFlight``. Both refuse beyond their configured
bounds (``LinkConfig``) instead of growing, and the gate counts every refusal by reason.
"""

from __future__ import annotations

import threading
from collections import Counter
from dataclasses import dataclass

from schemas.intake import KeyedBuckets, TokenBucket
from sim.clock import Clock

from .config import LinkConfig


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
