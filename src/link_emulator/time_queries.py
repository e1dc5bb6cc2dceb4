"""Vehicles' time queries through the link emulator: up a pair's channel, replies back down it.

A query heard on a vehicle's session is drawn through that pair's uplink channel and, unless
lost, forwarded on the RSU session when due; every RSU reply is drawn through the same
pair's downlink channel and answered on the vehicle's query when due. The query stays open
(``ForwardedQuery``) until the RSU's get has finished and no reply is in flight; each pair
keeps at most ``max_open_queries``. Zenoh callbacks only stamp and enqueue; the rest runs in
the relay's scheduler thread (``relay.py``).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from v2i.core.clock import Clock

from link_emulator.config import LinkConfig
from link_emulator.gate import Gate
from link_emulator.pair import Delivery, VehiclePair
from link_emulator.scheduler import EventScheduler

FORWARD_TIMEOUT_S = 5.0  # how long a forwarded time query waits for RSU replies


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


class TimeQueryRelay:
    """Forwards vehicles' time queries to the RSU session (``rsu``, set once it is open)."""

    def __init__(self, config: LinkConfig, clock: Clock, scheduler: EventScheduler, gate: Gate,
                 record: Callable[[VehiclePair, Delivery], None],
                 distance_m: Callable[[VehiclePair], float | None]) -> None:
        self.config = config
        self.rsu: zenoh.Session | None = None
        self._clock, self._scheduler, self._gate = clock, scheduler, gate
        self._record, self._distance_m = record, distance_m
        self._query_ids = itertools.count()

    @staticmethod
    def drop_open(pairs: list[VehiclePair]) -> None:
        """Finalise every open query (unanswered) at shutdown."""
        for pair in pairs:
            for forwarded in pair.queries.values():
                forwarded.query.drop()
            pair.queries.clear()

    def on_query(self, pair: VehiclePair, query: zenoh.Query) -> None:
        """Zenoh callback (a vehicle side): stamp and enqueue; the query is kept for the reply."""
        receive_ns = self._clock.now_ns()
        size = len(query.payload) if query.payload is not None else 0
        if not self._gate.admit(pair.gate_key(str(query.key_expr)), size):
            query.drop()
            return
        self._scheduler.push(receive_ns, lambda _: self._query_arrival(pair, query, receive_ns))

    def _query_arrival(self, pair: VehiclePair, query: zenoh.Query, receive_ns: int) -> None:
        """Draw the uplink fate of a query on its pair's channel; a lost query is dropped unanswered."""
        self._gate.done()
        pair.uplink.received += 1
        payload = query.payload.to_bytes() if query.payload is not None else None
        due_ns = pair.model.uplink.transmit(receive_ns, len(payload or b""), distance_m=self._distance_m(pair))
        if due_ns is None:
            pair.uplink.dropped += 1
            query.drop()
            return
        if len(pair.queries) >= self.config.max_open_queries or not pair.in_flight["uplink"].reserve(
                len(payload or b""), self.config):
            self._gate.count("too_many_open_queries")
            query.drop()
            return
        query_id = next(self._query_ids)
        pair.queries[query_id] = ForwardedQuery(query)
        selector, encoding = str(query.selector), query.encoding

        def forward(fired_ns: int) -> None:
            pair.in_flight["uplink"].release(len(payload or b""))
            handler = zenoh.handlers.Callback(
                lambda reply: self._on_rsu_reply(pair, query_id, reply), lambda: self._on_rsu_get_done(pair, query_id)
            )
            self.rsu.get(
                selector,
                handler,
                payload=payload,
                encoding=encoding if payload is not None else None,
                timeout=FORWARD_TIMEOUT_S,
                consolidation=zenoh.ConsolidationMode.NONE,
            )
            self._record(pair, Delivery("uplink", selector, payload, receive_ns, due_ns, fired_ns,
                                                 pair.vehicle_id))

        self._scheduler.push(due_ns, forward)

    def _on_rsu_reply(self, pair: VehiclePair, query_id: int, reply: zenoh.Reply) -> None:
        """Zenoh callback (RSU side): copy the reply out, stamp and enqueue."""
        receive_ns = self._clock.now_ns()
        body = reply.ok if reply.ok is not None else reply.err
        # bucketed per pair: V vehicles' replies share the RSU's key (20 at 10 Hz exceed one key's rate)
        key = f"reply {reply.ok.key_expr}" if reply.ok is not None else "reply_err"
        if not self._gate.admit(pair.gate_key(key), len(body.payload)):
            return
        if reply.ok is not None:
            copied = RsuReply(True, str(reply.ok.key_expr), reply.ok.payload.to_bytes(), reply.ok.encoding)
        else:
            copied = RsuReply(False, None, reply.err.payload.to_bytes(), reply.err.encoding)
        self._scheduler.push(receive_ns, lambda _: self._reply_arrival(pair, query_id, copied, receive_ns))

    def _on_rsu_get_done(self, pair: VehiclePair, query_id: int) -> None:
        """Zenoh callback: the forwarded get has finished; enqueue the bookkeeping."""
        self._scheduler.push(self._clock.now_ns(), lambda _: self._rsu_get_done(pair, query_id))

    def _reply_arrival(self, pair: VehiclePair, query_id: int, reply: RsuReply, receive_ns: int) -> None:
        """Draw the downlink fate of one reply on the pair's channel; schedule it back unless lost."""
        self._gate.done()
        forwarded = pair.queries.get(query_id)
        if forwarded is None:
            return
        pair.downlink.received += 1
        due_ns = pair.model.downlink.transmit(receive_ns, len(reply.payload), distance_m=self._distance_m(pair))
        if due_ns is None:
            pair.downlink.dropped += 1
            return
        if not pair.in_flight["downlink"].reserve(len(reply.payload), self.config):
            self._gate.count("in_flight_full")
            return
        forwarded.pending_replies += 1

        def deliver(fired_ns: int) -> None:
            pair.in_flight["downlink"].release(len(reply.payload))
            try:
                self._send_reply(forwarded.query, reply)
                self._record(pair, Delivery("downlink", reply.key or "", reply.payload, receive_ns, due_ns,
                                                     fired_ns, pair.vehicle_id))
            finally:
                forwarded.pending_replies -= 1
                self._finish_if_complete(pair, query_id)

        self._scheduler.push(due_ns, deliver)

    @staticmethod
    def _send_reply(query: zenoh.Query, reply: RsuReply) -> None:
        """Answer the vehicle's query with the RSU's reply (or error reply)."""
        if reply.ok:
            query.reply(reply.key, reply.payload, encoding=reply.encoding)
        else:
            query.reply_err(reply.payload, encoding=reply.encoding)

    def _rsu_get_done(self, pair: VehiclePair, query_id: int) -> None:
        forwarded = pair.queries.get(query_id)
        if forwarded is not None:
            forwarded.rsu_get_done = True
            self._finish_if_complete(pair, query_id)

    def _finish_if_complete(self, pair: VehiclePair, query_id: int) -> None:
        """Drop (finalise) the vehicle's query once the RSU is done and no reply is in flight."""
        forwarded = pair.queries.get(query_id)
        if forwarded is not None and forwarded.rsu_get_done and forwarded.pending_replies == 0:
            del pair.queries[query_id]
            forwarded.query.drop()
