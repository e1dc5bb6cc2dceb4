"""The link emulator process: two Zenoh sessions and a timed relay between them.

One session is connected to the RSU side only, one to the vehicle side only; the relay is
their only path. Downlink: RSU object lists and predictions are re-published on the
vehicle side after a downlink delay (or dropped). Time queries from the vehicle are
forwarded to the RSU after an uplink delay; each reply returns after a downlink delay.
Ego poses heard on the vehicle side, with the configured RSU position, give the channel
model the vehicle-RSU distance (unknown until both are known).

Runtime control: ``LinkControl`` messages on ``v2x/link/{link_id}/control`` (heard on both
sessions; the vehicle-side one also listens on ``control_listen`` for controllers) switch the
profile or add an impairment window (``control.apply_control``). Bad ones are counted by
reason in the stats and logged once per reason.

Zenoh callbacks only stamp the receive time and enqueue. One scheduler thread (the one
calling ``run``) owns the channel models, the counters and the pending queries, and fires
every action from a heap of ``(due_ns, seq, action)`` when it falls due (``scheduler``).

Peers on either side cannot make the emulator hold without bound: a callback passes a
``Gate`` first (payload size, a token bucket per key, a cap on arrivals not yet drawn),
messages in flight are capped per direction in number and bytes (beyond, dropped as a full
radio buffer would), and so are the vehicle's open time queries. Every refusal is counted by
reason in the stats (``refused``).
"""

from __future__ import annotations

import itertools
import json
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from schemas.codec import CodecError, decode
from schemas.keys import (
    RSU_IMAGE_FEATURES_ALL,
    RSU_OBJECTS_ALL,
    RSU_PREDICTIONS_ALL,
    RSU_TIME_ALL,
    link_control,
    link_stats,
)
from schemas.messages import EgoPose, LinkControl
from schemas.runtime import MemoryTrim
from schemas.transport import open_session
from sim.clock import Clock

from .channel import NS_PER_MS, LinkModel
from .config import LinkConfig
from .control import apply_control
from .gate import Gate, InFlight, VehiclePosition
from .stats import ControlStats, DirectionStats, RunningStats
from .profile import LinkProfile, load_profile
from .scheduler import Action, EventScheduler

log = logging.getLogger(__name__)

DOWNLINK_KEYS = (RSU_OBJECTS_ALL, RSU_PREDICTIONS_ALL, RSU_IMAGE_FEATURES_ALL)
FORWARD_TIMEOUT_S = 5.0  # how long a forwarded time query waits for RSU replies
OBU_POSE_ALL = "v2x/obu/*/pose"  # ego poses of every vehicle, see schemas.keys.obu_pose


@dataclass(frozen=True)
class Delivery:
    """One relayed message, reported to an observer right after it was sent on.

    ``due_ns - receive_ns`` is the drawn link delay; ``fired_ns - due_ns`` the relay's lateness.
    """

    direction: str  # "downlink" or "uplink"
    key: str
    payload: bytes | None
    receive_ns: int
    due_ns: int
    fired_ns: int


DeliveryObserver = Callable[[Delivery], None]


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

    def __init__(self, config: LinkConfig, clock: Clock, observer: DeliveryObserver | None = None) -> None:
        self.config = config
        self.ready = threading.Event()
        self._clock = clock
        self._model = LinkModel(load_profile(config.profile), config.seed)
        self._scheduler = EventScheduler(clock)
        self._uplink = DirectionStats()
        self._downlink = DirectionStats()
        self._lateness_ms = RunningStats()
        self._position = VehiclePosition(config.vehicle_id)
        self._control = ControlStats()
        self._gate = Gate(config, clock)
        self._trim = MemoryTrim()
        self._in_flight = {"uplink": InFlight(), "downlink": InFlight()}
        self._queries: dict[int, ForwardedQuery] = {}
        self._query_ids = itertools.count()
        self._declared: list[Any] = []  # subscribers and queryables to undeclare
        self._observer = observer  # benchmarks and tests: sees every delivery, in the scheduler thread
        self._rsu: zenoh.Session | None = None
        self._vehicle: zenoh.Session | None = None

    @property
    def profile(self) -> LinkProfile:
        """The profile in force (a control message may have switched it)."""
        return self._model.profile

    # ---- life cycle -------------------------------------------------------------------

    def open(self) -> None:
        """Open both sessions and declare the subscribers and the time queryable."""
        try:
            self._rsu = open_session(connect=self.config.rsu_connect)
            self._vehicle = open_session(listen=self.config.control_listen, connect=self.config.vehicle_connect)
            for key in DOWNLINK_KEYS:
                self._declared.append(self._rsu.declare_subscriber(key, self._on_rsu_sample))
            for session in (self._rsu, self._vehicle):
                self._declared.append(session.declare_subscriber(link_control(self.config.link_id),
                                                                 self._on_control_sample))
            self._declared.append(self._vehicle.declare_queryable(RSU_TIME_ALL, self._on_vehicle_query))
            self._declared.append(self._vehicle.declare_subscriber(OBU_POSE_ALL, self._on_pose_sample))
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
            "pose": self._position.as_dict(self.config.rsu_position),
            "open_queries": len(self._queries),
            "in_flight": {d: {"messages": f.messages, "bytes": f.bytes} for d, f in self._in_flight.items()},
            "refused": self._gate.snapshot(),
            "control": self._control.as_dict(),
        }

    def _stats_action(self, period_ns: int) -> Action:
        """An action publishing stats on both sides, then rescheduling itself one period later."""
        key = link_stats(self.config.link_id)

        def publish(fired_ns: int) -> None:
            self._scheduler.push(fired_ns + period_ns, publish)
            payload = json.dumps(self.stats_snapshot(fired_ns)).encode()
            for session in (self._rsu, self._vehicle):
                session.put(key, payload, encoding=zenoh.Encoding.APPLICATION_JSON)
            self._trim.maybe()

        return publish

    def _record_delivery(self, delivery: Delivery) -> None:
        """Count one delivered message: delay = fired - received, lateness = fired - due (ms)."""
        stats = self._downlink if delivery.direction == "downlink" else self._uplink
        stats.delivered += 1
        stats.delay_ms.add((delivery.fired_ns - delivery.receive_ns) / NS_PER_MS)
        self._lateness_ms.add((delivery.fired_ns - delivery.due_ns) / NS_PER_MS)
        if self._observer is not None:
            self._observer(delivery)

    # ---- runtime control ---------------------------------------------------------------

    def _on_control_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh callback (either side): stamp and enqueue; decoding and applying are the scheduler's."""
        receive_ns = self._clock.now_ns()
        if not self._gate.admit(str(sample.key_expr), len(sample.payload)):
            return
        payload = sample.payload.to_bytes()
        self._scheduler.push(receive_ns, lambda _: self._control_arrival(payload, receive_ns))

    def _control_arrival(self, payload: bytes, receive_ns: int) -> None:
        """Apply one LinkControl as of its receipt; a bad one is counted and logged once per reason."""
        self._gate.done()
        try:
            control = decode(payload, LinkControl)
        except CodecError as exc:
            self._reject_control(f"codec_{exc.reason}", None, str(exc))
            return
        if control.link_id != self.config.link_id:
            self._reject_control("wrong_link_id", control.seq,
                                 f"link_id {control.link_id!r}, this emulator is {self.config.link_id!r}")
            return
        try:
            result = apply_control(self._model, control, receive_ns)
        except ValueError as exc:
            self._reject_control("unknown_profile" if control.profile is not None else "invalid", control.seq, str(exc))
            return
        self._control.apply(control.seq, result)
        log.info("link control (seq %d): %s", control.seq, result)

    def _reject_control(self, reason: str, seq: int | None, error: str) -> None:
        if self._control.reject(reason, seq, error):
            log.warning("rejected a link control message (%s: %s); further ones are only counted", reason, error)

    # ---- vehicle position: ego poses for distance-dependent channels ----------------------

    def _on_pose_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh callback (vehicle side): enqueue; decoding is the scheduler thread's job."""
        if not self._gate.admit(str(sample.key_expr), len(sample.payload)):
            return
        payload = sample.payload.to_bytes()
        self._scheduler.push(self._clock.now_ns(), lambda _: self._pose_arrival(payload))

    def _pose_arrival(self, payload: bytes) -> None:
        """Keep the vehicle's position from an ego pose; an undecodable pose is counted and ignored."""
        self._gate.done()
        try:
            pose = decode(payload, EgoPose)
        except CodecError as exc:
            self._position.rejected += 1
            if self._position.rejected == 1:  # a broken publisher would flood the log at 10 Hz
                log.warning("ignored an undecodable ego pose (%s); further ones are only counted", exc)
            return
        self._position.take(pose)

    def _distance_m(self) -> float | None:
        """Vehicle-RSU distance (m) for the channel model; None while unknown."""
        return self._position.distance_m(self.config.rsu_position)

    # ---- downlink: object lists and predictions -----------------------------------------

    def _on_rsu_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh callback (RSU side): stamp and enqueue."""
        receive_ns = self._clock.now_ns()
        key = str(sample.key_expr)
        if not self._gate.admit(key, len(sample.payload)):
            return
        payload, encoding = sample.payload.to_bytes(), sample.encoding
        self._scheduler.push(receive_ns, lambda _: self._sample_arrival(key, payload, encoding, receive_ns))

    def _sample_arrival(self, key: str, payload: bytes, encoding: zenoh.Encoding, receive_ns: int) -> None:
        """Draw the downlink fate of one sample; schedule its delivery unless lost."""
        self._gate.done()
        self._downlink.received += 1
        due_ns = self._model.downlink.transmit(receive_ns, len(payload), distance_m=self._distance_m())
        if due_ns is None:
            self._downlink.dropped += 1
            return
        if not self._in_flight["downlink"].reserve(len(payload), self.config):
            self._gate.count("in_flight_full")
            return

        def deliver(fired_ns: int) -> None:
            self._in_flight["downlink"].release(len(payload))
            self._vehicle.put(key, payload, encoding=encoding)
            self._record_delivery(Delivery("downlink", key, payload, receive_ns, due_ns, fired_ns))

        self._scheduler.push(due_ns, deliver)

    # ---- time queries: uplink request, downlink replies --------------------------------

    def _on_vehicle_query(self, query: zenoh.Query) -> None:
        """Zenoh callback (vehicle side): stamp and enqueue; the query is kept for the reply."""
        receive_ns = self._clock.now_ns()
        if not self._gate.admit(str(query.key_expr), len(query.payload) if query.payload is not None else 0):
            query.drop()
            return
        self._scheduler.push(receive_ns, lambda _: self._query_arrival(query, receive_ns))

    def _query_arrival(self, query: zenoh.Query, receive_ns: int) -> None:
        """Draw the uplink fate of a query; a lost query is dropped unanswered."""
        self._gate.done()
        self._uplink.received += 1
        payload = query.payload.to_bytes() if query.payload is not None else None
        due_ns = self._model.uplink.transmit(receive_ns, len(payload or b""), distance_m=self._distance_m())
        if due_ns is None:
            self._uplink.dropped += 1
            query.drop()
            return
        if len(self._queries) >= self.config.max_open_queries or not self._in_flight["uplink"].reserve(
                len(payload or b""), self.config):
            self._gate.count("too_many_open_queries")
            query.drop()
            return
        query_id = next(self._query_ids)
        self._queries[query_id] = ForwardedQuery(query)
        selector, encoding = str(query.selector), query.encoding

        def forward(fired_ns: int) -> None:
            self._in_flight["uplink"].release(len(payload or b""))
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
            self._record_delivery(Delivery("uplink", selector, payload, receive_ns, due_ns, fired_ns))

        self._scheduler.push(due_ns, forward)

    def _on_rsu_reply(self, query_id: int, reply: zenoh.Reply) -> None:
        """Zenoh callback (RSU side): copy the reply out, stamp and enqueue."""
        receive_ns = self._clock.now_ns()
        body = reply.ok if reply.ok is not None else reply.err
        if not self._gate.admit(str(reply.ok.key_expr) if reply.ok is not None else "reply_err", len(body.payload)):
            return
        if reply.ok is not None:
            copied = RsuReply(True, str(reply.ok.key_expr), reply.ok.payload.to_bytes(), reply.ok.encoding)
        else:
            copied = RsuReply(False, None, reply.err.payload.to_bytes(), reply.err.encoding)
        self._scheduler.push(receive_ns, lambda _: self._reply_arrival(query_id, copied, receive_ns))

    def _on_rsu_get_done(self, query_id: int) -> None:
        """Zenoh callback: the forwarded get has finished; enqueue the bookkeeping."""
        self._scheduler.push(self._clock.now_ns(), lambda _: self._rsu_get_done(query_id))

    def _reply_arrival(self, query_id: int, reply: RsuReply, receive_ns: int) -> None:
        """Draw the downlink fate of one reply; schedule it back to the vehicle unless lost."""
        self._gate.done()
        forwarded = self._queries.get(query_id)
        if forwarded is None:
            return
        self._downlink.received += 1
        due_ns = self._model.downlink.transmit(receive_ns, len(reply.payload), distance_m=self._distance_m())
        if due_ns is None:
            self._downlink.dropped += 1
            return
        if not self._in_flight["downlink"].reserve(len(reply.payload), self.config):
            self._gate.count("in_flight_full")
            return
        forwarded.pending_replies += 1

        def deliver(fired_ns: int) -> None:
            self._in_flight["downlink"].release(len(reply.payload))
            try:
                self._send_reply(forwarded.query, reply)
                self._record_delivery(Delivery("downlink", reply.key or "", reply.payload, receive_ns, due_ns, fired_ns))
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
