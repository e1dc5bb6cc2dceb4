"""Timed impairment windows: runtime changes to a channel, e.g. from a chaos tool.

A window applies to every message whose send time falls in ``[start_ns, end_ns)``.
Overlapping windows combine: any outage drops, extra delays add, the highest loss
probability and the lowest bandwidth win.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

DIRECTIONS = ("uplink", "downlink", "both")


@dataclass(frozen=True)
class Impairment:
    """One window; ``loss_probability`` (Bernoulli) and ``bandwidth_kbps`` replace the profile's."""

    start_ns: int
    end_ns: int
    outage: bool = False
    extra_delay_ms: float = 0.0
    loss_probability: float | None = None
    bandwidth_kbps: float | None = None

    def __post_init__(self) -> None:
        if self.end_ns <= self.start_ns:
            raise ValueError(f"impairment end_ns ({self.end_ns}) must be after start_ns ({self.start_ns})")
        if not (math.isfinite(self.extra_delay_ms) and self.extra_delay_ms >= 0.0):
            raise ValueError(f"impairment extra_delay_ms must be finite and >= 0, got {self.extra_delay_ms}")
        if self.loss_probability is not None and not 0.0 <= self.loss_probability <= 1.0:
            raise ValueError(f"impairment loss_probability must be in [0, 1], got {self.loss_probability}")
        if self.bandwidth_kbps is not None and not self.bandwidth_kbps > 0.0:
            raise ValueError(f"impairment bandwidth_kbps must be > 0, got {self.bandwidth_kbps}")


class Effects(NamedTuple):
    """Per-message effect of the active windows, arrays of shape (n,)."""

    outage: np.ndarray  # bool
    extra_delay_ms: np.ndarray  # float, 0 outside windows
    loss_probability: np.ndarray  # float, NaN where no window overrides the loss
    bandwidth_kbps: np.ndarray  # float, NaN where no window overrides the rate


def effects(windows: list[Impairment], send_ns: np.ndarray) -> Effects:
    """The combined effect of ``windows`` on messages sent at ``send_ns`` (int64 ns, shape (n,))."""
    outage = np.zeros(send_ns.shape, dtype=bool)
    extra_ms = np.zeros(send_ns.shape)
    loss = np.full(send_ns.shape, np.nan)
    bandwidth = np.full(send_ns.shape, np.nan)
    for w in windows:
        active = (send_ns >= w.start_ns) & (send_ns < w.end_ns)
        if not active.any():
            continue
        outage |= active & w.outage
        extra_ms += np.where(active, w.extra_delay_ms, 0.0)
        if w.loss_probability is not None:
            loss = np.where(active, np.fmax(loss, w.loss_probability), loss)
        if w.bandwidth_kbps is not None:
            bandwidth = np.where(active, np.fmin(bandwidth, w.bandwidth_kbps), bandwidth)
    return Effects(outage, extra_ms, loss, bandwidth)
