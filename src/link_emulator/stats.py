"""The link emulator's counters, published in its stats (``v2x/link/{id}/stats``)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

RECENT_CONTROLS = 16  # control outcomes repeated in every stats message


@dataclass
class RunningStats:
    """Count, mean, min and max of a stream of values (one unit, e.g. ms)."""

    count: int = 0
    total: float = 0.0
    minimum: float = float("inf")
    maximum: float = float("-inf")

    def add(self, value: float) -> None:
        self.count += 1
        self.total += value
        self.minimum = min(self.minimum, value)
        self.maximum = max(self.maximum, value)

    def as_dict(self) -> dict[str, float | int | None]:
        if self.count == 0:
            return {"count": 0, "mean": None, "min": None, "max": None}
        return {"count": self.count, "mean": self.total / self.count, "min": self.minimum, "max": self.maximum}


@dataclass
class DirectionStats:
    """Messages of one direction: received by the relay, delivered, dropped; delays in ms."""

    received: int = 0
    delivered: int = 0
    dropped: int = 0
    delay_ms: RunningStats = field(default_factory=RunningStats)

    def as_dict(self) -> dict[str, Any]:
        return {
            "received": self.received,
            "delivered": self.delivered,
            "dropped": self.dropped,
            "delay_ms": self.delay_ms.as_dict(),
        }


@dataclass
class ControlStats:
    """LinkControl messages: how many were applied, rejections by reason, and the latest outcomes.

    ``recent`` holds the last ``RECENT_CONTROLS`` outcomes with the message's ``seq`` so that a
    controller can tell that its own message was handled (``v2i link set``, ``v2i chaos run``):
    ``{"seq", "result"}`` when applied, ``{"seq", "rejected", "error"}`` when not (seq None when
    the message could not be decoded).
    """

    applied: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    recent: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=RECENT_CONTROLS))

    def apply(self, seq: int, result: str) -> None:
        self.applied += 1
        self.recent.append({"seq": seq, "result": result})

    def reject(self, reason: str, seq: int | None, error: str) -> bool:
        """Count a rejection; True when it is the first one for ``reason`` (log it then)."""
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        self.recent.append({"seq": seq, "rejected": reason, "error": error})
        return self.rejected[reason] == 1

    def as_dict(self) -> dict[str, Any]:
        return {"applied": self.applied, "rejected": dict(self.rejected), "recent": list(self.recent)}
