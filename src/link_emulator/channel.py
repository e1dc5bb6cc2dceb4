"""Seeded channel models: when, whether and how often a message sent at a given time arrives.

Pure: no clock reads, no I/O. Time is an argument; randomness comes from an injected
``numpy.random.Generator``. One implementation serves the live relay (one message per
call) and the offline evaluator and validator (a batch per call): a batch of n messages
gives exactly what n single calls give.

A message of ``size`` bytes sent at ``t`` (ns) in one direction, in send order:

1. outage (profile ``outage`` or an impairment window): ``drop`` loses it; ``hold``
   makes it available at the end of the window, ``a = end``, else ``a = t``;
2. send queue, when there is a rate R (``bandwidth_kbps``): serialization
   ``s = 8 size / R`` and Lindley's recursion ``depart_k = max(a_k, depart_{k-1}) + s_k``;
   a message that would wait longer than ``queue_limit_ms`` is dropped (tail drop);
3. loss: the Gilbert-Elliott / Bernoulli chain, a lost trace slot at ``depart``, and, when
   the distance d is known, a Bernoulli loss with probability ``1 - PDR(d)`` (0 beyond ``range_m``);
4. delay: ``deliver = depart + max(0, delay_ms + g(z_k) + spike + trace + extra)``, with
   ``z_k`` the AR(1) score of ``processes.GaussianAR1``, ``g`` the jitter transform and
   ``trace`` the order-keeping replay delay of ``processes.TraceClock`` at ``depart`` (exact
   integer ns: without jitter or spikes a replay never reorders);
5. a delivered message is duplicated with ``duplicate_probability``: the copy is queued
   right after it and gets a fresh, uncorrelated jitter draw;
6. ``fifo``: ``deliver_k = max(deliver_k, deliver_j for every earlier delivered j)``.

Each message consumes a fixed set of variates (3 normals, 5 uniforms, drawn in blocks),
so the random stream of message k never depends on the fate of earlier messages.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from link_emulator.channel_scalar import (_U_DUP, _U_IMPAIR, _U_LOSS, _U_PDR, _U_SPIKE, _Z_DUP, _Z_JITTER,  # noqa: F401
                             _Z_SPIKE, NONE_NS, ScalarPath, _clipped_ns, _interp, _jitter_ms)
from link_emulator.impairment import DIRECTIONS, Effects, Impairment, effects
from link_emulator.processes import (
    NS_PER_MS,
    GaussianAR1,
    GilbertElliott,
    OutageTimeline,
    TraceClock,
)
from link_emulator.profile import DirectionProfile, LinkProfile
from link_emulator.trace import load_trace

__all__ = ["NS_PER_MS", "Channel", "Deliveries", "Impairment", "LinkModel"]

# Tail-drop limit of the send queue under a runtime bandwidth cap when the profile sets none
# (like netem's default packet limit): without one, a cap below the offered load would delay
# everything after it by the whole backlog, long after the cap is lifted.
IMPAIRMENT_QUEUE_LIMIT_MS = 500.0

_INT64_MIN = np.iinfo(np.int64).min


class Deliveries(NamedTuple):
    """Fate of a batch of messages, arrays of shape (n,), int64 ns on the sender's clock."""

    deliver_ns: np.ndarray  # the message's delivery time, NONE_NS when lost
    duplicate_ns: np.ndarray  # its copy's delivery time, NONE_NS when not duplicated

    @property
    def lost(self) -> np.ndarray:
        """True where the message was lost, shape (n,)."""
        return self.deliver_ns == NONE_NS


class _Draws:
    """Per-message variates from one generator, drawn in blocks of a fixed size."""

    BLOCK = 1024

    def __init__(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self.normal = np.empty((0, 3))  # the current block (rows from ``_pos`` on not yet taken)
        self._uniform = np.empty((0, 5))
        self._columns: tuple[list, list] | None = None  # the block's columns as Python floats, once asked for
        self._pos = 0

    def _have(self, n: int) -> None:
        """At least n rows left in the block: the rest, then new blocks, become the block."""
        if self._pos + n > len(self.normal):
            blocks = -(-(self._pos + n - len(self.normal)) // self.BLOCK)
            normal, uniform = [self.normal[self._pos:]], [self._uniform[self._pos:]]
            for _ in range(blocks):
                normal.append(self._rng.standard_normal((self.BLOCK, 3)))
                uniform.append(self._rng.random((self.BLOCK, 5)))
            self.normal, self._uniform = np.concatenate(normal), np.concatenate(uniform)
            self._pos, self._columns = 0, None

    def take(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The next n messages' variates: normals (n, 3) and uniforms (n, 5)."""
        self._have(n)
        start, self._pos = self._pos, self._pos + n
        return self.normal[start:self._pos], self._uniform[start:self._pos]

    def take_one(self) -> tuple[int, list[list[float]], list[list[float]]]:
        """The next message's row k of the block, and the block's columns as Python floats: normals (3
        columns), uniforms (5); its variates are ``z[c][k]`` and ``u[c][k]`` (a column's ``tolist`` makes
        a block's floats without a list per row: ~100 vs ~265 us a block)."""
        k = self._pos
        if k >= len(self.normal):  # _have(1)
            self._have(1)
            k = self._pos
        columns = self._columns
        if columns is None:
            columns = self._columns = (self.normal.T.tolist(), self._uniform.T.tolist())
        self._pos = k + 1
        return k, columns[0], columns[1]


class Channel(ScalarPath):
    """One direction of a link; see the module docstring for what happens to a message (one message on a
    plain channel: ``channel_scalar.ScalarPath``)."""

    def __init__(self, direction: DirectionProfile, rng: np.random.Generator) -> None:
        setup_rng, self._outage_rng = rng.spawn(2)
        self._draws = _Draws(rng)
        self._z0, self._u_bad0, self._u_phase = setup_rng.standard_normal(), setup_rng.random(), setup_rng.random()
        self._impairments: list[Impairment] = []
        self._g_kept: dict[int, tuple[np.ndarray, object, list[float]]] = {}  # column -> (block, jitter, g(z))
        self._free_ns = _INT64_MIN  # when the send queue is next free
        self._last_ns = _INT64_MIN  # latest delivery so far (for fifo)
        self._ar: GaussianAR1 | None = None
        self._ge: GilbertElliott | None = None
        self.set_direction(direction)

    # ---- configuration ----------------------------------------------------------------

    def set_direction(self, direction: DirectionProfile) -> None:
        """Impose a new profile from the next message on (chain, queue and order state kept).

        Time-based processes (outage schedule, trace replay) restart at the next message.
        """
        self.direction = direction
        self._pdr_curve = None if direction.pdr_curve is None else tuple([float(v) for v in c]
                                                                          for c in zip(*direction.pdr_curve))
        self._ar = GaussianAR1(direction.correlation, self._ar.z if self._ar else self._z0)
        bad0 = self._ge.bad if self._ge else self._u_bad0 < direction.loss_probability
        self._ge = GilbertElliott(direction.loss_probability, direction.mean_burst_len, bad0)
        self._outages = OutageTimeline(direction.outage, self._outage_rng) if direction.outage else None
        self._trace = None
        if direction.replay is not None:
            trace = load_trace(direction.replay.trace)
            self._trace = TraceClock(trace, int(self._u_phase * trace.loop_ms * NS_PER_MS))
        self._origin_ns: int | None = None
        self._plain_now = self._plain()

    def add_impairment(self, impairment: Impairment) -> None:
        """Apply ``impairment`` to messages sent inside its window."""
        self._impairments.append(impairment)
        self._plain_now = False

    def clear_impairments(self) -> None:
        """Forget every impairment window."""
        self._impairments.clear()
        self._plain_now = self._plain()

    # ---- transmission -----------------------------------------------------------------

    def transmit(self, send_time_ns: int, size_bytes: int, distance_m: float | None = None) -> int | None:
        """First delivery time in ns (same clock as ``send_time_ns``), or None when lost.

        ``distance_m``: sender-receiver distance; None (unknown) applies no distance loss.
        """
        times = self.transmit_all(send_time_ns, size_bytes, distance_m)
        return times[0] if times else None

    def transmit_all(self, send_time_ns: int, size_bytes: int, distance_m: float | None = None) -> list[int]:
        """Every delivery of one message in ns, ascending: [] lost, two entries when duplicated."""
        if self._plain_now:  # _plain(), kept by set_direction and the impairment methods
            return self._transmit_one(int(send_time_ns), size_bytes, distance_m)
        out = self.transmit_batch(np.array([send_time_ns]), size_bytes, distance_m)
        times = [int(t) for t in (out.deliver_ns[0], out.duplicate_ns[0]) if t != NONE_NS]
        return sorted(times)

    def _plain(self) -> bool:
        """No impairment window, outage schedule, trace replay or rate cap: stages 1, 2 and the
        trace pass every message through unchanged."""
        return not self._impairments and self._outages is None and self._trace is None \
            and self.direction.bandwidth_kbps is None

    def transmit_batch(
        self, send_ns: np.ndarray, size_bytes: np.ndarray | int, distance_m: np.ndarray | float | None = None
    ) -> Deliveries:
        """Fates of n messages given in send order: ``send_ns`` int64 (n,), sizes and distances (n,) or scalar.

        A NaN distance is unknown. Equivalent to n calls of ``transmit_all``.
        """
        send = np.asarray(send_ns, dtype=np.int64).reshape(-1)
        size = np.asarray(size_bytes, dtype=np.int64)
        if size.size and size.min() < 0:
            raise ValueError(f"size_bytes must be >= 0, got {int(size.min())}")
        if size.ndim and size.shape != send.shape:
            raise ValueError(f"size_bytes must be a scalar or shaped like send_ns {send.shape}, got {size.shape}")
        normal, uniform = self._draws.take(send.size)
        if send.size == 0:
            return Deliveries(send.copy(), send.copy())
        if self._origin_ns is None:
            self._origin_ns = int(send[0])
        rel_ns = send - self._origin_ns
        fx = effects(self._impairments, send) if self._impairments else None
        avail_ns, dropped = self._availability(send, rel_ns.astype(float), fx)
        lost = dropped | self._loss(uniform, distance_m, fx)
        dup = ~lost & (uniform[:, _U_DUP] < self.direction.duplicate_probability)
        depart_ns, dup_depart_ns, queue_drop = self._queue(avail_ns, size, ~dropped, dup, fx)
        trace_ns, trace_lost = self._replay(depart_ns)
        prop_ns = self._delay_ns(normal, uniform, trace_ns, fx)
        lost |= queue_drop | trace_lost
        deliver = np.where(lost, NONE_NS, depart_ns + prop_ns)
        copy = np.full(send.shape, NONE_NS, dtype=np.int64)
        if dup.any():
            dup &= ~(queue_drop | trace_lost)
            copy_ns = self._copy_delay_ns(normal[:, _Z_DUP], trace_ns, fx)
            copy = np.where(dup, dup_depart_ns + copy_ns, NONE_NS)
        return self._in_order(deliver, copy)

    # ---- stages -------------------------------------------------------------------------

    def _availability(self, send: np.ndarray, rel_ns: np.ndarray, fx: Effects | None) -> tuple[np.ndarray, np.ndarray]:
        """When each message can be sent (ns) and whether an outage dropped it."""
        dropped = fx.outage.copy() if fx is not None else np.zeros(send.shape, dtype=bool)
        if self._outages is None:
            return send, dropped
        until_ns = self._outages.down_until(rel_ns)
        down = ~np.isnan(until_ns)
        if self._outages.spec.mode == "drop":
            return send, dropped | down
        release = self._origin_ns + np.ceil(np.where(down, until_ns, 0.0)).astype(np.int64)
        return np.where(down, release, send), dropped

    def _replay(self, depart_ns: np.ndarray) -> tuple[np.ndarray | int, np.ndarray | bool]:
        """Trace delay (int64 ns) and trace loss of messages entering the network at ``depart_ns``.

        Looked up at the departure, not the send time: departures are non-decreasing (FIFO
        queue, outage hold), so the order-keeping replay keeps the send order.
        """
        if self._trace is None:
            return 0, False
        return self._trace.delay_ns(depart_ns - self._origin_ns)

    def _delay_ns(
        self, normal: np.ndarray, uniform: np.ndarray, trace_ns: np.ndarray | int, fx: Effects | None
    ) -> np.ndarray:
        """Propagation delay (int64 ns, >= 0) of each message: max(0, delay_ms + g(z) + spike + extra + trace)."""
        d = self.direction
        z = self._ar.step(normal[:, _Z_JITTER])
        delay_ms = d.delay_ms + d.jitter.from_normal(z)
        if d.spikes is not None:
            spike_ms = d.spikes.extra.from_normal(normal[:, _Z_SPIKE])
            delay_ms = delay_ms + np.where(uniform[:, _U_SPIKE] < d.spikes.probability, spike_ms, 0.0)
        return _clipped_sum_ns(delay_ms + _extra_ms(fx), trace_ns)

    def _copy_delay_ns(self, z_dup: np.ndarray, trace_ns: np.ndarray | int, fx: Effects | None) -> np.ndarray:
        """A duplicate's delay (int64 ns, >= 0): base + an independent jitter draw + the shared extra and trace."""
        d = self.direction
        return _clipped_sum_ns(d.delay_ms + d.jitter.from_normal(z_dup) + _extra_ms(fx), trace_ns)

    def _loss(self, uniform: np.ndarray, distance_m: np.ndarray | float | None, fx: Effects | None) -> np.ndarray:
        """Lost on the air: the loss chain (or an impairment's Bernoulli) and distance PDR."""
        bad = self._ge.step(uniform[:, _U_LOSS])
        if fx is not None:
            override = ~np.isnan(fx.loss_probability)
            if override.any():
                bad = np.where(override, uniform[:, _U_IMPAIR] < fx.loss_probability, bad)
        if distance_m is not None:
            d = np.broadcast_to(np.asarray(distance_m, dtype=float), bad.shape)
            known = ~np.isnan(d)
            # delivered with probability PDR(d): lost when u >= PDR(d)
            bad = bad | (known & (uniform[:, _U_PDR] >= self.direction.pdr_at(np.where(known, d, 0.0))))
        return bad

    def _queue(
        self, avail_ns: np.ndarray, size: np.ndarray, sent: np.ndarray, dup: np.ndarray, fx: Effects | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Departure times of messages and copies and tail drops, by Lindley's recursion."""
        no_override = fx is None or np.isnan(fx.bandwidth_kbps).all()
        if self.direction.bandwidth_kbps is None and no_override:
            return avail_ns, avail_ns, np.zeros(avail_ns.shape, dtype=bool)
        rate_kbps = np.full(avail_ns.shape, self.direction.bandwidth_kbps or np.inf)
        if not no_override:
            rate_kbps = np.where(np.isnan(fx.bandwidth_kbps), rate_kbps, fx.bandwidth_kbps)
        # s = 8 size / R: bits / (kbit/s) = ms, so ns = 8e6 size / R_kbps
        tx_ns = np.rint(np.where(np.isinf(rate_kbps), 0.0, 8e6 * size / rate_kbps)).astype(np.int64)
        limit_ms = self.direction.queue_limit_ms
        if limit_ms is None and not no_override:
            limit_ms = IMPAIRMENT_QUEUE_LIMIT_MS  # a runtime rate cap must not build an unbounded backlog
        limit_ns = None if limit_ms is None else round(limit_ms * NS_PER_MS)
        depart, dup_depart, drop, self._free_ns = _lindley(
            avail_ns.tolist(), tx_ns.tolist(), sent.tolist(), dup.tolist(), limit_ns, self._free_ns
        )
        return np.array(depart, dtype=np.int64), np.array(dup_depart, dtype=np.int64), np.array(drop, dtype=bool)

    def _in_order(self, deliver: np.ndarray, copy: np.ndarray) -> Deliveries:
        """Apply ``fifo`` over messages and copies in send order; track the latest delivery."""
        if deliver.size == 1:  # the live per-message path; the same rule as below
            times = self._one_in_order(int(deliver[0]), int(copy[0]))
            return Deliveries(*(np.array([t], dtype=np.int64) for t in times))
        seq = np.column_stack((deliver, copy)).reshape(-1)
        valid = seq != NONE_NS
        latest = np.maximum.accumulate(np.concatenate(([self._last_ns], np.where(valid, seq, _INT64_MIN))))[1:]
        self._last_ns = int(latest[-1])
        if self.direction.fifo:
            seq = np.where(valid, latest, NONE_NS).reshape(-1, 2)
            return Deliveries(seq[:, 0].copy(), seq[:, 1].copy())
        return Deliveries(deliver, copy)


def _extra_ms(fx: Effects | None) -> np.ndarray | float:
    """Impairment extra delay (ms) of each message, shared by a message and its copy."""
    return fx.extra_delay_ms if fx is not None else 0.0


def _clipped_sum_ns(other_ms: np.ndarray, trace_ns: np.ndarray | int) -> np.ndarray:
    """max(0, other + trace) in int64 ns, the trace's part kept exact: trace + max(rint(other), -trace).

    ``other_ms`` (n,) in ms; ``trace_ns`` (n,) int64, or 0 without a trace. Exact integer trace
    delays keep a replay's equal arrival times equal (no 1 ns reordering from rounding).
    """
    if isinstance(trace_ns, int):  # no trace: the same arithmetic, fewer steps on the live path
        return np.rint(np.maximum(other_ms, 0.0) * NS_PER_MS).astype(np.int64)
    return trace_ns + np.maximum(np.rint(other_ms * NS_PER_MS).astype(np.int64), -trace_ns)


def _lindley(
    avail: list[int], tx: list[int], sent: list[bool], dup: list[bool], limit_ns: int | None, free_ns: int
) -> tuple[list[int], list[int], list[bool], int]:
    """FIFO send queue: depart = max(avail, free) + tx for each message (and its copy) in order.

    Returns departures, copies' departures, tail drops (wait > limit_ns) and the new free time.
    """
    depart, dup_depart, drop = list(avail), list(avail), [False] * len(avail)
    for k, (a_ns, s_ns) in enumerate(zip(avail, tx)):
        if not sent[k]:
            continue
        start_ns = max(a_ns, free_ns)
        if limit_ns is not None and start_ns - a_ns > limit_ns:
            drop[k] = True
            continue
        free_ns = depart[k] = start_ns + s_ns
        if dup[k]:
            free_ns = dup_depart[k] = free_ns + s_ns
    return depart, dup_depart, drop, free_ns


class LinkModel:
    """Uplink (vehicle -> RSU) and downlink (RSU -> vehicle) channels for a profile.

    The two channels use independent generators spawned from ``SeedSequence(seed)``, so
    traffic in one direction never shifts the random stream of the other; the same seed
    gives the same delays and losses. ``switch_profile`` and ``add_impairment`` change
    the link at run time (pure: the caller decides when).
    """

    def __init__(self, profile: LinkProfile, seed: int) -> None:
        self.profile = profile
        self.seed = seed
        uplink_seq, downlink_seq = np.random.SeedSequence(seed).spawn(2)
        self.uplink = Channel(profile.uplink, np.random.default_rng(uplink_seq))
        self.downlink = Channel(profile.downlink, np.random.default_rng(downlink_seq))

    def channels(self, direction: str) -> list[Channel]:
        """The channels named by ``direction``: 'uplink', 'downlink' or 'both'."""
        if direction not in DIRECTIONS:
            raise ValueError(f"direction must be one of {', '.join(DIRECTIONS)}, got {direction!r}")
        return {"uplink": [self.uplink], "downlink": [self.downlink], "both": [self.uplink, self.downlink]}[direction]

    def switch_profile(self, profile: LinkProfile) -> None:
        """Impose ``profile`` on both directions from their next message on."""
        self.profile = profile
        self.uplink.set_direction(profile.uplink)
        self.downlink.set_direction(profile.downlink)

    def add_impairment(
        self,
        start_ns: int,
        end_ns: int,
        direction: str = "both",
        outage: bool = False,
        extra_delay_ms: float = 0.0,
        loss_probability: float | None = None,
        bandwidth_kbps: float | None = None,
    ) -> Impairment:
        """Impair messages sent in ``[start_ns, end_ns)`` on ``direction``; returns the window.

        ``outage`` drops them; ``extra_delay_ms`` delays them; ``loss_probability`` replaces
        the profile's loss by a Bernoulli loss; ``bandwidth_kbps`` replaces the send rate.
        """
        channels = self.channels(direction)
        window = Impairment(start_ns, end_ns, outage, extra_delay_ms, loss_probability, bandwidth_kbps)
        for channel in channels:
            channel.add_impairment(window)
        return window

    def clear_impairments(self) -> None:
        """Remove every impairment window from both directions."""
        self.uplink.clear_impairments()
        self.downlink.clear_impairments()
