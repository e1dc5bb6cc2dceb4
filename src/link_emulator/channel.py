"""Seeded channel models: when (or whether) a message sent at a given time is delivered.

Pure: no clock reads, no I/O. Time is an argument; randomness comes from an injected
``numpy.random.Generator``. Each message is an independent draw (loss, then jitter).
"""

from __future__ import annotations

import numpy as np

from .profile import DirectionProfile, LinkProfile

NS_PER_MS = 1_000_000


class Channel:
    """One direction of a link: delay = max(0, base + jitter) (ms), Bernoulli loss."""

    def __init__(self, direction: DirectionProfile, rng: np.random.Generator) -> None:
        self.direction = direction
        self._rng = rng

    def draw_delay_ms(self) -> float | None:
        """One message's one-way delay in ms, or None when it is lost.

        Both the loss and the jitter draw are always consumed, so the random stream of
        message k does not depend on the fate of earlier messages.
        """
        lost = self._rng.random() < self.direction.loss_probability
        jitter_ms = self.direction.jitter.draw_ms(self._rng)
        if lost:
            return None
        # D = max(0, base + J): a message never arrives before it was sent.
        return max(0.0, self.direction.delay_ms + jitter_ms)

    def transmit(self, send_time_ns: int, size_bytes: int) -> int | None:
        """Delivery time in ns (same clock as ``send_time_ns``), or None when lost.

        ``size_bytes`` must be >= 0; the bundled delay models are size-independent (they
        describe short safety messages whose air time is part of the base delay).
        """
        if size_bytes < 0:
            raise ValueError(f"size_bytes must be >= 0, got {size_bytes}")
        delay_ms = self.draw_delay_ms()
        if delay_ms is None:
            return None
        return send_time_ns + round(delay_ms * NS_PER_MS)


class LinkModel:
    """Uplink (vehicle -> RSU) and downlink (RSU -> vehicle) channels for a profile.

    The two channels use independent generators spawned from ``SeedSequence(seed)``, so
    traffic in one direction never shifts the random stream of the other; the same seed
    gives the same delays and losses.
    """

    def __init__(self, profile: LinkProfile, seed: int) -> None:
        self.profile = profile
        self.seed = seed
        uplink_seq, downlink_seq = np.random.SeedSequence(seed).spawn(2)
        self.uplink = Channel(profile.uplink, np.random.default_rng(uplink_seq))
        self.downlink = Channel(profile.downlink, np.random.default_rng(downlink_seq))
