"""The V2V link emulator (``v2i link --v2v``): vehicles' messages to each other through a channel
per ordered vehicle pair.

Design: one V2V emulator per site, next to the one emulator per RSU (``relay.py``). A V2V
channel joins two vehicles, not a vehicle and an RSU, so it belongs to no RSU's emulator;
putting it in one would tie the vehicles' sidelink to that RSU's process (killed with it,
and absent where no RSU is in range), and one emulator per vehicle would need every other
vehicle's session too (V^2 sessions instead of V). So: one process with one Zenoh session per
vehicle (connected only to that vehicle's endpoints, as the RSU emulators' are) and V (V - 1)
channels, one per ordered pair (sender -> receiver), each its own ``LinkModel`` seeded by
``pair_seed(seed, "sender>receiver")`` (a pair keeps its draws when others join), its own
in-flight caps and counters. A sidelink message is a broadcast, but each receiver gets it or
loses it on its own (its distance, its collisions), hence one channel per receiver.

What it relays: from vehicle a's session, only a's own ``v2x/v2v/{a}/**`` (its shared list,
its time requests, its time replies; ``schemas.keys``), so no vehicle can speak for another
through the emulator; each message is transmitted independently on the (a, b) channel of
every other vehicle b (the profile's downlink direction, whatever the message: one radio) at
the a-b distance from their latest ego poses (``v2x/obu/{id}/pose``, each on its own
session, ``gate.VehiclePosition``; unknown distance: no distance loss) and re-published on
b's session after its delay, or dropped. The emulator is the only path between vehicles.

Control and stats as the RSU emulator's: ``LinkControl`` on ``v2x/link/{link_id}/control``
applies to every pair, or to every pair a vehicle it names sends or receives on; stats on
``v2x/link/{link_id}/stats`` (every session) carry the sums and, under ``pairs``, each
ordered pair's counters and distance. Zenoh callbacks stamp and enqueue only (through the
``Gate``: size, a token bucket per vehicle and key, pending arrivals); one scheduler thread
owns the channels and fires deliveries from a heap (``scheduler``).
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import zenoh

from schemas.codec import CodecError, decode
from schemas.keys import link_control, link_stats, obu_pose, v2v_from
from schemas.messages import EgoPose
from v2i.runtime.process import MemoryTrim
from v2i.runtime.transport import open_session
from v2i.core.clock import Clock
from v2i.telemetry.latency import StageLatency

from link_emulator.channel import NS_PER_MS, LinkModel
from link_emulator.config import LinkConfig
from link_emulator.control import admitted_control, apply_control
from link_emulator.control_auth import ControlAuth
from link_emulator.gate import Gate, InFlight, VehiclePosition
from link_emulator.pair import Delivery, merged_direction, pair_seed
from link_emulator.profile import load_profile
from link_emulator.scheduler import EventScheduler
from link_emulator.stats import ControlStats, DirectionStats, RunningStats

__all__ = ["V2vPair", "V2vRelay"]

log = logging.getLogger(__name__)


@dataclass
class V2vPair:
    """One ordered vehicle pair's channel and counters (scheduler thread only)."""

    sender: str
    receiver: str
    model: LinkModel
    stats: DirectionStats = field(default_factory=DirectionStats)
    in_flight: InFlight = field(default_factory=InFlight)

    def as_dict(self, distance_m: float | None) -> dict[str, Any]:
        return {"from": self.sender, "to": self.receiver, "profile": self.model.profile.name,
                "distance_m": distance_m, **self.stats.as_dict(),
                "in_flight": {"messages": self.in_flight.messages, "bytes": self.in_flight.bytes}}


class V2vRelay:
    """Relays vehicle -> vehicle traffic through one ``LinkModel`` per ordered pair; see the module docstring.

    ``open`` and ``run`` are called from one thread, which becomes the scheduler thread;
    ``ready`` is set once every session is open and declared.
    """

    def __init__(self, config: LinkConfig, clock: Clock, observer=None) -> None:
        if not config.v2v:
            raise ValueError("V2vRelay needs a LinkConfig with v2v set")
        self.config = config
        self.ready = threading.Event()
        self._clock = clock
        profile = load_profile(config.profile)
        self._ids = [v.vehicle_id for v in config.vehicles]
        self._pairs = {(a, b): V2vPair(a, b, LinkModel(profile, pair_seed(config.seed, f"{a}>{b}")))
                       for a in self._ids for b in self._ids if a != b}
        self._positions = {vid: VehiclePosition(vid) for vid in self._ids}
        self._scheduler = EventScheduler(clock)
        self._gate = Gate(config, clock)
        self._lateness_ms = RunningStats()
        self._control = ControlStats()
        self.control_auth = ControlAuth.create(config.link_id, config.pki, config.insecure_control,
                                        config.control_max_age_s, config.control_max_ahead_s)
        self._trim = MemoryTrim()
        self._observer = observer  # tests and benchmarks: every delivery, in the scheduler thread
        self.latency = StageLatency()  # relay_hold, relay_late (v2i.telemetry.latency); read by other threads
        self.last_stats: dict[str, Any] | None = None  # the latest published stats; one assignment
        self._declared: list[Any] = []
        self._sessions: dict[str, zenoh.Session] = {}
        self._control_session: zenoh.Session | None = None

    @property
    def pairs(self) -> dict[tuple[str, str], V2vPair]:
        return self._pairs

    # ---- life cycle -------------------------------------------------------------------
    def open(self) -> None:
        """Open every vehicle's session (and the control one), then declare the subscribers."""
        try:
            if self.config.control_listen:
                self._control_session = open_session(listen=self.config.control_listen)
            for vehicle in self.config.vehicles:
                self._sessions[vehicle.vehicle_id] = open_session(connect=vehicle.connect)
            for vid, session in self._sessions.items():
                self._declared.append(session.declare_subscriber(v2v_from(vid), lambda s, v=vid: self._on_sample(v, s)))
                self._declared.append(session.declare_subscriber(obu_pose(vid), lambda s, v=vid: self._on_pose(v, s)))
            for session in self._all_sessions():
                self._declared.append(session.declare_subscriber(link_control(self.config.link_id), self._on_control))
        except BaseException:
            self._close()
            raise
        self.ready.set()

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

    def _all_sessions(self) -> list[zenoh.Session]:
        return [s for s in (self._control_session, *self._sessions.values()) if s is not None]

    def _close(self) -> None:
        for declared in reversed(self._declared):
            declared.undeclare()
        self._declared.clear()
        self._scheduler.clear()
        for session in reversed(self._all_sessions()):
            session.close()
        self._sessions, self._control_session = {}, None
        self.ready.clear()

    # ---- relaying -----------------------------------------------------------------------
    def _on_sample(self, sender: str, sample: zenoh.Sample) -> None:
        """Zenoh callback (the sender's session): stamp and enqueue."""
        receive_ns = self._clock.now_ns()
        key = str(sample.key_expr)
        if not self._gate.admit(f"{sender}|{key}", len(sample.payload)):
            return
        payload, encoding = sample.payload.to_bytes(), sample.encoding
        self._scheduler.push(receive_ns, lambda _: self._arrival(sender, key, payload, encoding, receive_ns))

    def _arrival(self, sender: str, key: str, payload: bytes, encoding: zenoh.Encoding, receive_ns: int) -> None:
        """Transmit one message on the channel of every other vehicle independently."""
        self._gate.done()
        self.latency.observe_ns("relay_intake", receive_ns, self._clock.now_ns())  # callback -> scheduler thread
        for receiver in self._ids:
            if receiver != sender:
                self._transmit(self._pairs[(sender, receiver)], key, payload, encoding, receive_ns)

    def _transmit(self, pair: V2vPair, key: str, payload: bytes, encoding: zenoh.Encoding, receive_ns: int) -> None:
        pair.stats.received += 1
        due_ns = pair.model.downlink.transmit(receive_ns, len(payload), distance_m=self.distance_m(pair))
        if due_ns is None:
            pair.stats.dropped += 1
            return
        if not pair.in_flight.reserve(len(payload), self.config):
            self._gate.count("in_flight_full")
            return
        session = self._sessions[pair.receiver]
        self.latency.observe_ns("relay_hold", receive_ns, due_ns)

        def deliver(fired_ns: int) -> None:
            pair.in_flight.release(len(payload))
            t0_ns = time.perf_counter_ns()
            session.put(key, payload, encoding=encoding)
            self.latency.observe_ns("relay_put", t0_ns, time.perf_counter_ns())
            self.latency.observe_ns("relay_late", due_ns, fired_ns)
            pair.stats.delivered += 1
            pair.stats.delay_ms.add((fired_ns - receive_ns) / NS_PER_MS)
            self._lateness_ms.add((fired_ns - due_ns) / NS_PER_MS)
            if self._observer is not None:
                self._observer(Delivery("v2v", key, payload, receive_ns, due_ns, fired_ns, pair.receiver))

        self._scheduler.push(due_ns, deliver)

    def distance_m(self, pair: V2vPair) -> float | None:
        """Sender-receiver distance (m) from their latest ego poses; None while either is unknown."""
        a, b = self._positions[pair.sender].xy_m, self._positions[pair.receiver].xy_m
        return None if a is None or b is None else math.hypot(a[0] - b[0], a[1] - b[1])

    def _on_pose(self, vid: str, sample: zenoh.Sample) -> None:
        """Zenoh callback: a vehicle's ego pose, decoded in the scheduler thread."""
        if not self._gate.admit(f"{vid}|{sample.key_expr}", len(sample.payload)):
            return
        payload = sample.payload.to_bytes()
        self._scheduler.push(self._clock.now_ns(), lambda _: self._pose_arrival(vid, payload))

    def _pose_arrival(self, vid: str, payload: bytes) -> None:
        self._gate.done()
        position = self._positions[vid]
        try:
            position.take(decode(payload, EgoPose))
        except CodecError as exc:
            position.rejected += 1
            if position.rejected == 1:
                log.warning("ignored an undecodable ego pose of %s (%s); further ones are only counted", vid, exc)

    # ---- control and stats ---------------------------------------------------------------
    def _on_control(self, sample: zenoh.Sample) -> None:
        receive_ns = self._clock.now_ns()
        if not self._gate.admit(str(sample.key_expr), len(sample.payload)):
            return
        payload = sample.payload.to_bytes()
        self._scheduler.push(receive_ns, lambda _: self._control_arrival(payload, receive_ns))

    def _control_arrival(self, payload: bytes, receive_ns: int) -> None:
        """Apply one LinkControl to every pair, or to the pairs of the vehicle it names."""
        self._gate.done()
        control = admitted_control(payload, self.config.link_id, self._control.reject, self.control_auth, receive_ns)
        if control is None:
            return
        vid = control.vehicle_id
        targets = [p for p in self._pairs.values() if vid is None or vid in (p.sender, p.receiver)]
        if not targets:
            self._control.reject("unknown_vehicle", control.seq, f"no vehicle {vid!r} on this emulator")
            return
        try:
            results = [apply_control(p.model, control, receive_ns) for p in targets]
        except ValueError as exc:
            self._control.reject("unknown_profile" if control.profile is not None else "invalid", control.seq, str(exc))
            return
        self._control.apply(control.seq, results[0] + (f" (vehicle {vid})" if vid is not None else ""))

    def stats_snapshot(self, t_ns: int) -> dict[str, Any]:
        """Sums over the ordered pairs (``v2v``) and each pair's own (``pairs``); delays in ms."""
        pairs = list(self._pairs.values())
        names = {p.model.profile.name for p in pairs}
        return {
            "link_id": self.config.link_id, "time_ns": t_ns, "mode": "v2v",
            "profile": names.pop() if len(names) == 1 else "mixed",
            "v2v": merged_direction([p.stats for p in pairs]),
            "pairs": [p.as_dict(self.distance_m(p)) for p in pairs],
            "pose": {vid: pos.as_dict(None) for vid, pos in self._positions.items()},
            "lateness_ms": self._lateness_ms.as_dict(),
            "refused": self._gate.snapshot(),
            "control": self._control.as_dict(),
            "latency_ms": self.latency.summary_ms(),
        }

    def _stats_action(self, period_ns: int):
        key = link_stats(self.config.link_id)

        def publish(fired_ns: int) -> None:
            self._scheduler.push(fired_ns + period_ns, publish)
            stats = self.stats_snapshot(fired_ns)
            self.last_stats = stats
            payload = json.dumps(stats).encode()
            for session in self._all_sessions():
                session.put(key, payload, encoding=zenoh.Encoding.APPLICATION_JSON)
            self._trim.maybe()

        return publish
