"""The link emulator process: one RSU-side Zenoh session, one session per vehicle, and a
timed relay between them through one channel per RSU-vehicle pair.

Design: one emulator process per RSU, serving every vehicle in its range (at most
``config.MAX_VEHICLES``). An RSU's radio is one transmitter: its channels to the vehicles
share its position and its traffic, so they belong together; a site-wide emulator for every
RSU would be a single point of failure and a bottleneck (one GIL for all the site's traffic),
while one per RSU scales with the RSUs and runs where the radio is.

Zenoh pub/sub cannot give two subscribers of one key different losses, so each vehicle has
its own session, connected only to that vehicle's endpoints, and its own ``VehiclePair``
(``pair.py``): its own ``LinkModel`` with its own seeded draws, its own distance (its poses on
``v2x/obu/{vehicle_id}/pose`` against ``rsu_position``), in-flight caps, open queries and stats.
The relay is the only path between the RSU and each vehicle. Downlink: an RSU object list,
prediction or image-feature message is transmitted independently on every pair's channel
and re-published on that vehicle's session after its delay (or dropped). Uplink: a vehicle's
time query goes up its own channel to the RSU; each reply comes back down the same pair's.
The one-vehicle form (``vehicle_connect``) is one pair whose vehicle is ``vehicle_id`` or
the first one heard, seeded by ``seed`` itself, exactly as before pairs existed.

Runtime control: ``LinkControl`` messages on ``v2x/link/{link_id}/control`` (heard on every
session, and on the control session listening on ``control_listen`` for controllers) switch
the profile or add an impairment window (``control.apply_control``) on every pair, or on the
pair of the vehicle they name (``vehicle_id``), once authenticated (``control_auth``: signed by
an operator with ``pki``, else refused unless ``insecure_control``). Bad ones are counted by
reason in the stats and logged once per reason. Stats (``v2x/link/{link_id}/stats``, on every
session) carry the sums over pairs and, under ``pairs``, each pair's own counters.

Zenoh callbacks only stamp the receive time and enqueue. One scheduler thread (the one
calling ``run``) owns the channel models, the counters and the pending queries, and fires
every action from a heap of ``(due_ns, seq, action)`` when it falls due (``scheduler``).

Peers on either side cannot make the emulator hold without bound: a callback passes a
``Gate`` first (payload size, a token bucket per key and vehicle, a cap on arrivals not yet
drawn), messages in flight are capped per pair and direction in number and bytes (beyond,
dropped as a full radio buffer would), and so are each vehicle's open time queries. Every
refusal is counted by reason in the stats (``refused``).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from schemas.codec import CodecError, decode
from schemas.keys import (
    RSU_CPM_ALL,
    RSU_IMAGE_FEATURES_ALL,
    RSU_OBJECTS_ALL,
    RSU_PREDICTIONS_ALL,
    RSU_SDSM_ALL,
    RSU_TIME_ALL,
    link_control,
    link_stats,
)
from schemas.messages import EgoPose
from v2i.runtime.process import MemoryTrim
from v2i.runtime.transport import open_session
from v2i.core.clock import Clock
from v2i.telemetry.latency import StageLatency

from link_emulator.channel import NS_PER_MS
from link_emulator.config import LinkConfig
from link_emulator.control import admitted_control
from link_emulator.control_auth import ControlAuth
from link_emulator.gate import Gate
from link_emulator.pair import Delivery, VehiclePair, apply_to_pairs, control_targets, pairs_summary
from link_emulator.profile import LinkProfile, load_profile
from link_emulator.scheduler import Action, EventScheduler
from link_emulator.stats import ControlStats, RunningStats
from link_emulator.time_queries import TimeQueryRelay

__all__ = ["Delivery", "DeliveryObserver", "LinkRelay"]

log = logging.getLogger(__name__)

DOWNLINK_KEYS = (RSU_OBJECTS_ALL, RSU_PREDICTIONS_ALL, RSU_IMAGE_FEATURES_ALL, RSU_CPM_ALL, RSU_SDSM_ALL)
OBU_POSE_ALL = "v2x/obu/*/pose"  # ego poses of every vehicle, see schemas.keys.obu_pose


DeliveryObserver = Callable[[Delivery], None]


class LinkRelay:
    """Relays RSU <-> vehicles traffic through one ``LinkModel`` per pair; see the module docstring.

    Thread model: ``open`` and ``run`` are called from one thread, which becomes the
    scheduler thread; ``ready`` is set once every session is open and declared.
    """

    def __init__(self, config: LinkConfig, clock: Clock, observer: DeliveryObserver | None = None) -> None:
        self.config = config
        self.ready = threading.Event()
        self._clock = clock
        profile = load_profile(config.profile)
        one_vehicle_form = bool(config.vehicle_connect)
        self._pairs = [VehiclePair.create(side, profile, config.seed, one_vehicle_form)
                       for side in config.vehicle_sides()]
        self._scheduler = EventScheduler(clock)
        self._lateness_ms = RunningStats()
        self._control = ControlStats()
        self.control_auth = ControlAuth.create(config.link_id, config.pki, config.insecure_control,
                                        config.control_max_age_s, config.control_max_ahead_s)
        self._gate = Gate(config, clock)
        self._trim = MemoryTrim()
        self._queries = TimeQueryRelay(config, clock, self._scheduler, self._gate, self._record_delivery,
                                       self._distance_m)
        self._declared: list[Any] = []  # subscribers and queryables to undeclare
        self._observer = observer  # benchmarks and tests: sees every delivery, in the scheduler thread
        self.latency = StageLatency()  # relay_hold, relay_late (v2i.telemetry.latency); read by other threads
        self.last_stats: dict[str, Any] | None = None  # the latest published stats; one assignment
        self._rsu: zenoh.Session | None = None
        self._control_session: zenoh.Session | None = None
        self._vehicles: list[zenoh.Session] = []  # one per pair, in pair order

    @property
    def profile(self) -> LinkProfile:
        """The profile in force on the first pair (a control message may have switched it)."""
        return self._pairs[0].model.profile

    @property
    def pairs(self) -> list[VehiclePair]:
        """The RSU-vehicle pairs, in configured order (scheduler thread, or after ``run``)."""
        return self._pairs

    # ---- life cycle -------------------------------------------------------------------

    def open(self) -> None:
        """Open every session, then declare the subscribers and the time queryables.

        Declared only once every session is open: opening 20 sessions takes seconds, and what
        arrived meanwhile would wait for the scheduler (``run``) and fire that late.
        """
        try:
            self._rsu = self._queries.rsu = open_session(connect=self.config.rsu_connect)
            if self.config.control_listen:
                self._control_session = open_session(listen=self.config.control_listen)
            for pair in self._pairs:  # appended one by one: a failure closes those already open
                self._vehicles.append(open_session(connect=pair.side.connect))
            for key in DOWNLINK_KEYS:
                self._declared.append(self._rsu.declare_subscriber(key, self._on_rsu_sample))
            for pair, session in zip(self._pairs, self._vehicles):
                self._declare_vehicle_side(pair, session)
            for session in self._sessions():
                self._declared.append(session.declare_subscriber(link_control(self.config.link_id),
                                                                 self._on_control_sample))
        except BaseException:
            self._close()
            raise
        self.ready.set()

    def _declare_vehicle_side(self, pair: VehiclePair, session: zenoh.Session) -> None:
        """The pair's time queryable and pose subscriber on its own session."""
        self._declared.append(session.declare_queryable(RSU_TIME_ALL, lambda q: self._queries.on_query(pair, q)))
        self._declared.append(session.declare_subscriber(OBU_POSE_ALL, lambda s: self._on_pose_sample(pair, s)))

    def run(self, stop: threading.Event) -> None:
        """Relay until ``stop`` is set, then undeclare everything and close every session."""
        try:
            if not self.ready.is_set():
                self.open()
            period_ns = round(self.config.stats_period_s * 1e9)
            self._scheduler.push(self._clock.now_ns() + period_ns, self._stats_action(period_ns))
            self._scheduler.run(stop)
        finally:
            self._close()

    def _sessions(self) -> list[zenoh.Session]:
        return [s for s in (self._rsu, self._control_session, *self._vehicles) if s is not None]

    def _close(self) -> None:
        """Undeclare, finalise open queries, drop in-flight messages, close the sessions."""
        for declared in reversed(self._declared):
            declared.undeclare()
        self._declared.clear()
        self._queries.drop_open(self._pairs)
        self._scheduler.clear()
        for session in reversed(self._sessions()):
            session.close()
        self._rsu = self._queries.rsu = self._control_session = None
        self._vehicles = []
        self.ready.clear()

    # ---- statistics -------------------------------------------------------------------

    def stats_snapshot(self, t_ns: int) -> dict[str, Any]:
        """Counters and delays (ms) at ``t_ns``; call from the scheduler thread or after ``run``.

        ``uplink``, ``downlink``, ``pose``, ``open_queries`` and ``in_flight`` are sums over the
        pairs, ``pairs`` each pair's own (``pair.pairs_summary``). ``lateness_ms`` is actual
        minus scheduled delivery time of relayed messages.
        """
        summary = pairs_summary(self._pairs, self.config.rsu_position)
        return {
            "link_id": self.config.link_id,
            "time_ns": t_ns,
            **summary,
            "lateness_ms": self._lateness_ms.as_dict(),
            "refused": self._gate.snapshot(),
            "control": self._control.as_dict(),
            "latency_ms": self.latency.summary_ms(),
        }

    def _stats_action(self, period_ns: int) -> Action:
        """An action publishing stats on every session, then rescheduling itself one period later."""
        key = link_stats(self.config.link_id)

        def publish(fired_ns: int) -> None:
            self._scheduler.push(fired_ns + period_ns, publish)
            stats = self.stats_snapshot(fired_ns)
            self.last_stats = stats
            payload = json.dumps(stats).encode()
            for session in self._sessions():
                session.put(key, payload, encoding=zenoh.Encoding.APPLICATION_JSON)
            self._trim.maybe()

        return publish

    def _record_delivery(self, pair: VehiclePair, delivery: Delivery) -> None:
        """Count one delivered message: delay = fired - received, lateness = fired - due (ms)."""
        stats = pair.direction(delivery.direction)
        stats.delivered += 1
        stats.delay_ms.add((delivery.fired_ns - delivery.receive_ns) / NS_PER_MS)
        self._lateness_ms.add((delivery.fired_ns - delivery.due_ns) / NS_PER_MS)
        if self._observer is not None:
            self._observer(delivery)

    # ---- runtime control ---------------------------------------------------------------

    def _on_control_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh callback (any session): stamp and enqueue; decoding and applying are the scheduler's."""
        receive_ns = self._clock.now_ns()
        if not self._gate.admit(str(sample.key_expr), len(sample.payload)):
            return
        payload = sample.payload.to_bytes()
        self._scheduler.push(receive_ns, lambda _: self._control_arrival(payload, receive_ns))

    def _control_arrival(self, payload: bytes, receive_ns: int) -> None:
        """Apply one LinkControl as of its receipt; a bad one is counted and logged once per reason."""
        self._gate.done()
        control = admitted_control(payload, self.config.link_id, self._reject_control, self.control_auth, receive_ns)
        if control is None:
            return
        targets = control_targets(self._pairs, control)
        if not targets:
            known = ", ".join(str(p.vehicle_id) for p in self._pairs)
            self._reject_control("unknown_vehicle", control.seq,
                                 f"no vehicle {control.vehicle_id!r} on this emulator (vehicles: {known})")
            return
        try:
            result = apply_to_pairs(targets, control, receive_ns)
        except ValueError as exc:
            self._reject_control("unknown_profile" if control.profile is not None else "invalid", control.seq, str(exc))
            return
        self._control.apply(control.seq, result)
        log.info("link control (seq %d): %s", control.seq, result)

    def _reject_control(self, reason: str, seq: int | None, error: str) -> None:
        if self._control.reject(reason, seq, error):
            log.warning("rejected a link control message (%s: %s); further ones are only counted", reason, error)

    # ---- vehicle position: ego poses for distance-dependent channels ----------------------

    def _on_pose_sample(self, pair: VehiclePair, sample: zenoh.Sample) -> None:
        """Zenoh callback (a vehicle side): enqueue; decoding is the scheduler thread's job."""
        if not self._gate.admit(pair.gate_key(str(sample.key_expr)), len(sample.payload)):
            return
        payload = sample.payload.to_bytes()
        self._scheduler.push(self._clock.now_ns(), lambda _: self._pose_arrival(pair, payload))

    def _pose_arrival(self, pair: VehiclePair, payload: bytes) -> None:
        """Keep the pair's vehicle position from an ego pose; an undecodable pose is counted and ignored."""
        self._gate.done()
        try:
            pose = decode(payload, EgoPose)
        except CodecError as exc:
            pair.position.rejected += 1
            if pair.position.rejected == 1:  # a broken publisher would flood the log at 10 Hz
                log.warning("ignored an undecodable ego pose (%s); further ones are only counted", exc)
            return
        pair.position.take(pose)

    def _distance_m(self, pair: VehiclePair) -> float | None:
        """Vehicle-RSU distance (m) for the pair's channel model; None while unknown."""
        return pair.position.distance_m(self.config.rsu_position)

    # ---- downlink: object lists and predictions, on every pair's channel ---------------

    def _on_rsu_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh callback (RSU side): stamp and enqueue."""
        receive_ns = self._clock.now_ns()
        key = str(sample.key_expr)
        if not self._gate.admit(key, len(sample.payload)):
            return
        payload, encoding = sample.payload.to_bytes(), sample.encoding
        self._scheduler.push(receive_ns, lambda _: self._sample_arrival(key, payload, encoding, receive_ns))

    def _sample_arrival(self, key: str, payload: bytes, encoding: zenoh.Encoding, receive_ns: int) -> None:
        """Transmit one RSU sample on every pair's downlink channel independently."""
        self._gate.done()
        self.latency.observe_ns("relay_intake", receive_ns, self._clock.now_ns())  # callback -> scheduler thread
        for index, pair in enumerate(self._pairs):
            self._transmit_down(index, pair, key, payload, encoding, receive_ns)

    def _transmit_down(self, index: int, pair: VehiclePair, key: str, payload: bytes, encoding: zenoh.Encoding,
                       receive_ns: int) -> None:
        """Draw the pair's downlink fate of one sample; schedule its delivery on the pair's session unless lost."""
        pair.downlink.received += 1
        due_ns = pair.model.downlink.transmit(receive_ns, len(payload), distance_m=self._distance_m(pair))
        if due_ns is None:
            pair.downlink.dropped += 1
            return
        if not pair.in_flight["downlink"].reserve(len(payload), self.config):
            self._gate.count("in_flight_full")
            return
        session = self._vehicles[index]
        self.latency.observe_ns("relay_hold", receive_ns, due_ns)

        def deliver(fired_ns: int) -> None:
            pair.in_flight["downlink"].release(len(payload))
            t0_ns = time.perf_counter_ns()
            session.put(key, payload, encoding=encoding)
            self.latency.observe_ns("relay_put", t0_ns, time.perf_counter_ns())
            self.latency.observe_ns("relay_late", due_ns, fired_ns)
            self._record_delivery(pair, Delivery("downlink", key, payload, receive_ns, due_ns, fired_ns,
                                                 pair.vehicle_id))

        self._scheduler.push(due_ns, deliver)
