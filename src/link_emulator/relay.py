"""The link emulator process: two Zenoh sessions and a timed relay between them.

One session is connected to the RSU side only, one to the vehicle side only; the relay is
their only path. Downlink: RSU object lists and predictions are re-published on the
vehicle side after a downlink delay (or dropped). Time queries from the vehicle are
forwarded to the RSU after an uplink delay; each reply returns after a downlink delay.

Zenoh callbacks only stamp the receive time and enqueue. One scheduler thread (the one
calling ``run``) owns the channel models, the counters and the pending queries, and fires
every action from a heap of ``(due_ns, seq, action)`` when it falls due.
"""

from __future__ import annotations

import heapq
import itertools
import json
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from schemas.keys import RSU_OBJECTS_ALL, RSU_PREDICTIONS_ALL, RSU_TIME_ALL, link_stats
from schemas.transport import open_session
from sim.clock import Clock

from .channel import NS_PER_MS, LinkModel
from .config import LinkConfig
from .profile import load_profile

log = logging.getLogger(__name__)

DOWNLINK_KEYS = (RSU_OBJECTS_ALL, RSU_PREDICTIONS_ALL)
FORWARD_TIMEOUT_S = 5.0  # how long a forwarded time query waits for RSU replies
MAX_WAIT_S = 0.05  # longest scheduler sleep, i.e. the latency of noticing ``stop``

Action = Callable[[int], None]  # called with the firing time in ns


class EventScheduler:
    """A heap of ``(due_ns, seq, action)``: any thread pushes, one thread fires in due order."""

    def __init__(self, clock: Clock, max_wait_s: float = MAX_WAIT_S) -> None:
        self._clock = clock
        self._max_wait_s = max_wait_s
        self._heap: list[tuple[int, int, Action]] = []
        self._seq = itertools.count()
        self._cond = threading.Condition()

    def push(self, due_ns: int, action: Action) -> None:
        """Schedule ``action(fired_ns)`` at ``due_ns`` (clock ns); thread-safe."""
        with self._cond:
            heapq.heappush(self._heap, (due_ns, next(self._seq), action))
            if self._heap[0][2] is action:
                self._cond.notify()

    def run(self, stop: threading.Event) -> None:
        """Fire due actions until ``stop`` is set; an action's exception is logged, not fatal."""
        while not stop.is_set():
            action = self._pop_due()
            if action is None:
                continue
            try:
                action(self._clock.now_ns())
            except Exception:
                log.exception("link relay action failed")

    def clear(self) -> int:
        """Forget every pending action; returns how many there were."""
        with self._cond:
            pending = len(self._heap)
            self._heap.clear()
            return pending

    def _pop_due(self) -> Action | None:
        """The head action if it is due, else None after sleeping until it is (at most max_wait_s)."""
        with self._cond:
            if not self._heap:
                self._cond.wait(self._max_wait_s)
                return None
            wait_s = (self._heap[0][0] - self._clock.now_ns()) / 1e9
            if wait_s > 0.0:
                self._cond.wait(min(wait_s, self._max_wait_s))
                return None
            return heapq.heappop(self._heap)[2]


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
class ForwardedQuery:
    """A vehicle time query forwarded to the RSU, kept open until all replies are relayed."""

    query: zenoh.Query
    pending_replies: int = 0  # replies scheduled for delivery, not yet sent
    rsu_get_done: bool = False  # the RSU-side get has finished (no more replies)


@dataclass(frozen=True)
class RsuReply:
    """One RSU reply, copied out of the Zenoh callback."""

    ok: bool
    key: str | None
    payload: bytes
    encoding: zenoh.Encoding | None


class LinkRelay:
    """Relays RSU <-> vehicle traffic through a ``LinkModel``; see the module docstring.

    Thread model: ``open`` and ``run`` are called from one thread, which becomes the
    scheduler thread; ``ready`` is set once both sessions are open and declared.
    """

    def __init__(self, config: LinkConfig, clock: Clock) -> None:
        self.config = config
        self.profile = load_profile(config.profile)
        self.ready = threading.Event()
        self._clock = clock
        self._model = LinkModel(self.profile, config.seed)
        self._scheduler = EventScheduler(clock)
        self._uplink = DirectionStats()
        self._downlink = DirectionStats()
        self._lateness_ms = RunningStats()
        self._queries: dict[int, ForwardedQuery] = {}
        self._query_ids = itertools.count()
        self._declared: list[Any] = []  # subscribers and queryables to undeclare
        self._rsu: zenoh.Session | None = None
        self._vehicle: zenoh.Session | None = None

    # ---- life cycle -------------------------------------------------------------------

    def open(self) -> None:
        """Open both sessions and declare the subscribers and the time queryable."""
        try:
            self._rsu = open_session(connect=self.config.rsu_connect)
            self._vehicle = open_session(connect=self.config.vehicle_connect)
            for key in DOWNLINK_KEYS:
                self._declared.append(self._rsu.declare_subscriber(key, self._on_rsu_sample))
            self._declared.append(self._vehicle.declare_queryable(RSU_TIME_ALL, self._on_vehicle_query))
        except BaseException:
            self._close()
            raise
        self.ready.set()

    def run(self, stop: threading.Event) -> None:
        """Relay until ``stop`` is set, then undeclare everything and close both sessions."""
        try:
            if not self.ready.is_set():
                self.open()
            period_ns = round(self.config.stats_period_s * 1e9)
            self._scheduler.push(self._clock.now_ns() + period_ns, self._stats_action(period_ns))
            self._scheduler.run(stop)
        finally:
            self._close()

    def _close(self) -> None:
        """Undeclare, finalise open queries, drop in-flight messages, close the sessions."""
        for declared in reversed(self._declared):
            declared.undeclare()
        self._declared.clear()
        for forwarded in self._queries.values():
            forwarded.query.drop()
        self._queries.clear()
        self._scheduler.clear()
        for session in (self._vehicle, self._rsu):
            if session is not None:
                session.close()
        self._rsu = self._vehicle = None
        self.ready.clear()

    # ---- statistics -------------------------------------------------------------------

    def stats_snapshot(self, t_ns: int) -> dict[str, Any]:
        """Counters and delays (ms) at ``t_ns``; call from the scheduler thread or after ``run``.

        ``lateness_ms`` is actual minus scheduled delivery time of relayed messages.
        """
        return {
            "link_id": self.config.link_id,
            "profile": self.profile.name,
            "time_ns": t_ns,
            "uplink": self._uplink.as_dict(),
            "downlink": self._downlink.as_dict(),
            "lateness_ms": self._lateness_ms.as_dict(),
            "open_queries": len(self._queries),
        }

    def _stats_action(self, period_ns: int) -> Action:
        """An action publishing stats on both sides, then rescheduling itself one period later."""
        key = link_stats(self.config.link_id)

        def publish(fired_ns: int) -> None:
            self._scheduler.push(fired_ns + period_ns, publish)
            payload = json.dumps(self.stats_snapshot(fired_ns)).encode()
            for session in (self._rsu, self._vehicle):
                session.put(key, payload, encoding=zenoh.Encoding.APPLICATION_JSON)

        return publish

    def _record_delivery(self, stats: DirectionStats, receive_ns: int, due_ns: int, fired_ns: int) -> None:
        """Count one delivered message: delay = fired - received, lateness = fired - due (ms)."""
        stats.delivered += 1
        stats.delay_ms.add((fired_ns - receive_ns) / NS_PER_MS)
        self._lateness_ms.add((fired_ns - due_ns) / NS_PER_MS)

    # ---- downlink: object lists and predictions -----------------------------------------

    def _on_rsu_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh callback (RSU side): stamp and enqueue."""
        receive_ns = self._clock.now_ns()
        key, payload, encoding = str(sample.key_expr), sample.payload.to_bytes(), sample.encoding
        self._scheduler.push(receive_ns, lambda _: self._sample_arrival(key, payload, encoding, receive_ns))

    def _sample_arrival(self, key: str, payload: bytes, encoding: zenoh.Encoding, receive_ns: int) -> None:
        """Draw the downlink fate of one sample; schedule its delivery unless lost."""
        self._downlink.received += 1
        due_ns = self._model.downlink.transmit(receive_ns, len(payload))
        if due_ns is None:
            self._downlink.dropped += 1
            return

        def deliver(fired_ns: int) -> None:
            self._vehicle.put(key, payload, encoding=encoding)
            self._record_delivery(self._downlink, receive_ns, due_ns, fired_ns)

        self._scheduler.push(due_ns, deliver)

    # ---- time queries: uplink request, downlink replies --------------------------------

    def _on_vehicle_query(self, query: zenoh.Query) -> None:
        """Zenoh callback (vehicle side): stamp and enqueue; the query is kept for the reply."""
        receive_ns = self._clock.now_ns()
        self._scheduler.push(receive_ns, lambda _: self._query_arrival(query, receive_ns))

    def _query_arrival(self, query: zenoh.Query, receive_ns: int) -> None:
        """Draw the uplink fate of a query; a lost query is dropped unanswered."""
        self._uplink.received += 1
        payload = query.payload.to_bytes() if query.payload is not None else None
        due_ns = self._model.uplink.transmit(receive_ns, len(payload or b""))
        if due_ns is None:
            self._uplink.dropped += 1
            query.drop()
            return
        query_id = next(self._query_ids)
        self._queries[query_id] = ForwardedQuery(query)
        selector, encoding = str(query.selector), query.encoding

        def forward(fired_ns: int) -> None:
            self._record_delivery(self._uplink, receive_ns, due_ns, fired_ns)
            handler = zenoh.handlers.Callback(
                lambda reply: self._on_rsu_reply(query_id, reply), lambda: self._on_rsu_get_done(query_id)
            )
            self._rsu.get(
                selector,
                handler,
                payload=payload,
                encoding=encoding if payload is not None else None,
                timeout=FORWARD_TIMEOUT_S,
                consolidation=zenoh.ConsolidationMode.NONE,
            )

        self._scheduler.push(due_ns, forward)

    def _on_rsu_reply(self, query_id: int, reply: zenoh.Reply) -> None:
        """Zenoh callback (RSU side): copy the reply out, stamp and enqueue."""
        receive_ns = self._clock.now_ns()
        if reply.ok is not None:
            sample = reply.ok
            copied = RsuReply(True, str(sample.key_expr), sample.payload.to_bytes(), sample.encoding)
        else:
            copied = RsuReply(False, None, reply.err.payload.to_bytes(), reply.err.encoding)
        self._scheduler.push(receive_ns, lambda _: self._reply_arrival(query_id, copied, receive_ns))

    def _on_rsu_get_done(self, query_id: int) -> None:
        """Zenoh callback: the forwarded get has finished; enqueue the bookkeeping."""
        self._scheduler.push(self._clock.now_ns(), lambda _: self._rsu_get_done(query_id))

    def _reply_arrival(self, query_id: int, reply: RsuReply, receive_ns: int) -> None:
        """Draw the downlink fate of one reply; schedule it back to the vehicle unless lost."""
        forwarded = self._queries.get(query_id)
        if forwarded is None:
            return
        self._downlink.received += 1
        due_ns = self._model.downlink.transmit(receive_ns, len(reply.payload))
        if due_ns is None:
            self._downlink.dropped += 1
            return
        forwarded.pending_replies += 1

        def deliver(fired_ns: int) -> None:
            try:
                self._send_reply(forwarded.query, reply)
                self._record_delivery(self._downlink, receive_ns, due_ns, fired_ns)
            finally:
                forwarded.pending_replies -= 1
                self._finish_if_complete(query_id)

        self._scheduler.push(due_ns, deliver)

    @staticmethod
    def _send_reply(query: zenoh.Query, reply: RsuReply) -> None:
        """Answer the vehicle's query with the RSU's reply (or error reply)."""
        if reply.ok:
            query.reply(reply.key, reply.payload, encoding=reply.encoding)
        else:
            query.reply_err(reply.payload, encoding=reply.encoding)

    def _rsu_get_done(self, query_id: int) -> None:
        forwarded = self._queries.get(query_id)
        if forwarded is not None:
            forwarded.rsu_get_done = True
            self._finish_if_complete(query_id)

    def _finish_if_complete(self, query_id: int) -> None:
        """Drop (finalise) the vehicle's query once the RSU is done and no reply is in flight."""
        forwarded = self._queries.get(query_id)
        if forwarded is not None and forwarded.rsu_get_done and forwarded.pending_replies == 0:
            del self._queries[query_id]
            forwarded.query.drop()
