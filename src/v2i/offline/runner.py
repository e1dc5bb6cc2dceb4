"""Offline, deterministic driver: the live pipelines fed from an event queue.

The RSU pipeline, the OBU's inbox and pipeline, the codec and the link channel model are the
very objects the services use; only the clock (simulated) and the transport (an event
queue instead of Zenoh) differ. A 30 s scenario runs in a few seconds.

V2V (the scenario's ``v2v``, or ``RunSpec.v2v``): after each output a vehicle sends its shared
list (``obu_service.peers.shared_list``) to every other vehicle, and with each time-sync tick a
peer time request; a peer answers ``PEER_REPLY_NS`` later. Every message from vehicle a to
vehicle b crosses the ordered pair's own ``LinkModel`` (the V2V profile's downlink direction,
seeded by (seed, a, b), at the a-b distance at send time), as the live V2V emulator does
(``link_emulator.v2v_relay``). The vehicles' OBUs share the true clock here, so each peer
clock estimate is its own error. Chaos link events act on the RSU links only.
"""

from __future__ import annotations

from array import array
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from v2i.core.jit import load_kernels
from v2i.offline.kernels import RUN_KERNEL_MODULES
from v2i.core.scheduler import Timeline
from link_emulator.channel import LinkModel
from link_emulator.control import apply_control
from link_emulator.profile import LinkProfile, load_profile
from obu_service.inbound_security import InboundSecurity, make_verifier
from obu_service.inbox import Inbox, Outcome
from obu_service.peers import PEER_REPLY_NS, shared_list
from obu_service.pipeline import ObuPipeline
from obu_service.source import OwnFrame
from v2i.perception.scoring import PerceptionTally
from rsu_service.cpm_segments import CpmSender
from rsu_service.pipeline import RsuPipeline, RsuPipelineConfig, Stamp, answer_time_request
from rsu_service.prediction import make_predictor
from rsu_service.time_answers import TimeAnswers
from rsu_service.source import Frame
from schemas import keys
from schemas.codec import CodecError, decode, encode
from schemas.list_wire import encode_list, list_key
from schemas.messages import FusedObjectList, ObjectList, TimeReply, TimeRequest
from v2i.security.envelope import Signer, sign
from v2i.security.site import memory_site
from v2i.runtime.wire_files import WireFiles
from v2i.sim.clock import SimClock, rsu_clock
from v2i.sim.maps import scenario_map
from v2i.sim.obu_sources import SimulatedVehicle
from v2i.sim.rsu_sources import make_source
from v2i.sim.scenario import RsuCameraConfig, V2vConfig, load_scenario
from v2i.sim.scenario_site import site_of
from v2i.sim.world import World

from v2i.offline.chaos import SERVICES, ChaosTimeline
from v2i.offline.decode_memo import DecodeMemo
from v2i.offline.spec import EVAL_EPOCH_NS, RunRecord, RunSpec, rsu_lists, site_report

RSU_REPLY_NS = 50_000  # RSU time between receiving a time query and answering it


class EventQueue:
    """Time-ordered callbacks (``v2i.core.scheduler.Timeline``); ties keep insertion order."""

    def __init__(self, clock: SimClock):
        self.clock = clock
        self._timeline: Timeline[tuple[Callable, tuple]] = Timeline()

    def at(self, t_ns: int, fn: Callable, *args) -> None:
        self._timeline.push(int(t_ns), (fn, args))

    def run(self) -> None:
        """Each callback at its time: the clock set to it, then called."""
        timeline = self._timeline
        while timeline:
            self.clock.t_ns, (fn, args) = timeline.pop()
            fn(*args)


@dataclass
class _Rsu:
    """One RSU of the site: its camera, its pipeline (restartable) and its drifting clock."""

    index: int
    cfg: RsuCameraConfig
    camera: object  # a rsu_service.source source
    pipeline: RsuPipeline
    clock: object  # v2i.sim.clock.DriftingClock
    signer: Signer | None  # RunSpec.security: signs what it sends as the live RSU does
    list_key: str  # its key expressions: object lists (in the run's wire), predictions, time queries
    predictions_key: str
    time_key: str
    cpm: CpmSender | None = None  # --cpm-rules: the CPMs of each list under the generation rules
    answers: TimeAnswers = field(default_factory=TimeAnswers)  # one answer per time query, as the live RSU

    @cached_property
    def xy(self) -> tuple[float, float]:
        return self.cfg.position.x, self.cfg.position.y


@dataclass
class _Vehicle:
    """One connected vehicle: its view of the world, sensing, OBU and record, and a link
    (``LinkModel``, own draws) to each RSU by RSU index."""

    name: str
    world: World
    sensing: SimulatedVehicle
    obu: ObuPipeline
    record: RunRecord
    links: list[LinkModel]
    security: InboundSecurity  # verifies RSU messages as the live OBU does (policy off: unsigned pass)
    inbox: Inbox  # the live OBU's way in for RSU messages (envelope, header, admission, body), this security's


class OfflineRun:
    """One scenario run: every RSU and every vehicle of the scenario, each vehicle with its own
    channel to each RSU. ``execute()`` returns the first vehicle's (the ego's) RunRecord;
    ``records`` holds every vehicle's, ``report()`` scores them all."""

    def __init__(self, spec: RunSpec, start_ns: int = EVAL_EPOCH_NS, link_profile: LinkProfile | None = None,
                 chaos: ChaosTimeline | None = None, link_series: bool = False, save_wire: str | None = None):
        """``chaos``: timed faults; its RSU clock step must already be in ``spec`` (``with_chaos``).
        ``link_profile``: every pair's profile (default: the RSU's ``link_profile``, else ``spec.profile``).
        ``link_series``: after each cycle, each record keeps the OBU's RSU link status (the metrics
        a live OBU publishes per cycle) for the run report (``RunRecord.links``; ~5 % slower).
        ``save_wire``: a folder where every RSU's lists are saved as sent (``--save-wire``; ``wire_files``)."""
        load_kernels(RUN_KERNEL_MODULES)  # the compiled loops, as the services run them (the codec's bit packing too)
        self.spec = spec
        self.link_series = link_series
        self.chaos = chaos
        self.scenario = load_scenario(spec.scenario)
        self.site = World(self.scenario, site=True)
        self.site_config = site_of(self.scenario, scenario_map(spec.scenario))  # what configures the services
        self.duration_s = spec.duration_s or self.scenario.duration_s
        self.start_ns = start_ns
        self.clock = SimClock(start_ns)
        self.queue = EventQueue(self.clock)
        self._ego_now: dict[str, tuple[int, tuple[float, float]]] = {}  # vehicle -> (t_ns, true x, y at t)
        self._memo = DecodeMemo()  # a broadcast's bytes are decoded once for all its receivers
        self.rsu_config = spec.rsu_config()
        self.obu_config = spec.obu_config()
        # RunSpec.security: an in-memory site PKI (the CA's trust, each RSU's and vehicle's identity)
        self.trust, self.identities = (memory_site(start_ns, [r.id for r in self.scenario.rsus],
                                                   [v.name for v in self.scenario.vehicles])
                                       if spec.security is not None else (None, {}))
        self.rsus = [self._new_rsu_site(k, cfg) for k, cfg in enumerate(self.scenario.rsus)]
        profiles = [link_profile or load_profile(cfg.link_profile or spec.profile) for cfg in self.scenario.rsus]
        self.vehicles = [self._new_vehicle(v, profiles) for v in range(len(self.scenario.vehicles))]
        self.v2v = v2v_config(self.scenario.v2v, spec.v2v)
        self.v2v_links = self._new_v2v_links() if self.v2v is not None else {}
        self.world = self.vehicles[0].world
        self.records = {v.name: v.record for v in self.vehicles}
        self.record = self.vehicles[0].record
        self.perception = {r.cfg.id: PerceptionTally.of_source(r.camera, r.xy) for r in self.rsus}
        self.record.perception = self.perception[self.rsus[0].cfg.id]
        self._down = {name: self._windows_ns(name) for name in SERVICES}
        self.list_bytes = array("I")  # the size of every RSU object list sent (rsu_lists_sent)
        self.wire_files = ({} if save_wire is None else  # RSU id -> its saved lists (v2i.runtime.wire_files)
                           {r.cfg.id: WireFiles(save_wire, r.cfg.id, spec.wire, "eval") for r in self.rsus})

    @property
    def link(self) -> LinkModel:
        """The ego's link to the first RSU (the single-link view of older callers)."""
        return self.vehicles[0].links[0]

    def _new_rsu_site(self, index: int, cfg: RsuCameraConfig) -> _Rsu:
        config = self.rsu_config.model_copy(update={"rsu_id": cfg.id})
        return _Rsu(index, cfg, make_source(config, self.site, self.start_ns), self._new_pipeline(cfg.id),
                    rsu_clock(config, self.clock, self.start_ns), Signer(self.identities[cfg.id]) if self.trust else None,
                    list_key(self.spec.wire, cfg.id), keys.rsu_predictions(cfg.id), keys.rsu_time(cfg.id),
                    self._new_cpm_sender())

    def _new_cpm_sender(self) -> CpmSender | None:
        """--cpm-rules: a freshly started RSU's CPM generation (no object sent yet); None without."""
        config = self.rsu_config
        return CpmSender(self._encode_list, config.cpm_mtu_bytes) if config.cpm_rules else None

    def _new_pipeline(self, rsu_id: str) -> RsuPipeline:
        """A freshly started RSU (a restart loses its tracks and restarts its sequence numbers)."""
        return RsuPipeline(RsuPipelineConfig(rsu_id=rsu_id, predict_ahead=self.rsu_config.predict_ahead),
                           make_predictor(self.rsu_config.predictor, self.site_config))

    def _new_vehicle(self, index: int, profiles: list[LinkProfile]) -> _Vehicle:
        name = self.scenario.vehicles[index].name
        world = World(self.scenario, ego=name)
        obu = ObuPipeline(self.obu_config.model_copy(update={"vehicle_id": name}).pipeline_config(self.site_config),
                          self.obu_config.lanes(self.site_config))
        # pair (RSU k, vehicle v) draws from its own stream; the first pair keeps the run's seed
        pair_seed = [self.spec.seed if index == k == 0 else [self.spec.seed, index, k] for k in range(len(profiles))]
        links = [LinkModel(p, seed) for p, seed in zip(profiles, pair_seed)]
        verifier = make_verifier(self.trust, self.spec.security or "off", self.obu_config.planning_max_age_s)
        security = InboundSecurity(verifier, obu.clock_offset, obu.reject)
        return _Vehicle(name, world, SimulatedVehicle(world, self.spec.seed, self.start_ns), obu,
                        RunRecord(world, self.start_ns, self.duration_s), links, security,
                        Inbox(obu, security, memo=self._memo, origin=self._origin))  # a broadcast's bytes read once for all

    def _new_v2v_links(self) -> dict[tuple[str, str], LinkModel]:
        """One channel per ordered vehicle pair (sender, receiver), its own draws; peers enabled."""
        profile = load_profile(self.v2v.link_profile)
        for vehicle in self.vehicles:
            vehicle.obu.enable_v2v(self.v2v.max_peers)
        return {(a.name, b.name): LinkModel(profile, [self.spec.seed, 1_000 + i, j])
                for i, a in enumerate(self.vehicles) for j, b in enumerate(self.vehicles) if a is not b}

    def _windows_ns(self, service: str) -> list[tuple[int, int]]:
        if self.chaos is None:
            return []
        return [(self.start_ns + round(a * 1e9), self.start_ns + round(b * 1e9))
                for a, b in self.chaos.down_windows(service, self.duration_s + 1.0)]

    def _up(self, service: str, t_ns: int | None = None) -> bool:
        windows = self._down[service]
        if not windows:  # (most runs: no chaos)
            return True
        t_ns = self.clock.t_ns if t_ns is None else t_ns
        return not any(a <= t_ns < b for a, b in windows)

    def _schedule_chaos(self) -> None:
        """Link events reach every pair's channel; an RSU restart restarts every RSU."""
        for event in self.chaos.sorted_events() if self.chaos else ():
            at_ns = self.start_ns + round(event.at_s * 1e9)
            control = event.link_control("eval")
            if control is not None:
                self.queue.at(at_ns, self._control_links, control)
            elif event.restart == "rsu":
                self.queue.at(at_ns, self._restart_rsus)

    def _control_links(self, control) -> None:
        for vehicle in self.vehicles:
            for link in vehicle.links:
                apply_control(link, control, self.clock.t_ns)

    def _restart_rsus(self) -> None:
        for rsu in self.rsus:
            rsu.pipeline = self._new_pipeline(rsu.cfg.id)
            rsu.cpm = self._new_cpm_sender()
            rsu.answers = TimeAnswers()

    def execute(self) -> RunRecord:
        self._schedule_chaos()
        for rsu in self.rsus:
            for t in rsu.camera.capture_times_ns(self.duration_s):
                self.queue.at(t, self._rsu_capture, rsu)
        end_ns = self.start_ns + round(self.duration_s * 1e9)
        for vehicle in self.vehicles:
            cycles = vehicle.sensing.cycle_times_ns(self.duration_s)
            vehicle.record.cycle_times_ns = cycles
            for t in cycles:
                self.queue.at(t, self._obu_capture, vehicle)
            for t in range(self.start_ns, end_ns, round(1e9 / self.obu_config.sync_rate_hz)):
                self.queue.at(t, self._obu_sync, vehicle)
        self.queue.run()
        for vehicle in self.vehicles:
            vehicle.record.covered_cycles = vehicle.obu.covered_cycles
            vehicle.record.rsu_deadline_misses = vehicle.obu.rsu_deadline_misses
            vehicle.record.rejected = dict(vehicle.obu.rejected)
            vehicle.record.mode_reasons = dict(vehicle.obu.mode_reasons)
            vehicle.record.rsu_lists = rsu_lists(vehicle.obu.metrics(end_ns))
            vehicle.record.clock_steps = {r.cfg.id: self._steps(vehicle.obu, r.cfg.id) for r in self.rsus}
        return self.record

    @staticmethod
    def _steps(obu: ObuPipeline, rsu_id: str) -> int:
        """The RSU clock steps the vehicle's estimator confirmed (0: never synced)."""
        est = obu.clock_offset(rsu_id)
        return 0 if est is None else est.steps

    def report(self, driver: str = "eval") -> dict:
        """The ego's report (``build_report``), with every vehicle's scores under ``vehicles``
        and every RSU's perception under ``rsus`` (call after ``execute``)."""
        report = site_report(self.spec, [(v.name, v.world, v.record) for v in self.vehicles],
                             {rid: tally.scores() for rid, tally in self.perception.items()}, driver)
        report["v2v"] = None if self.v2v is None else self.v2v.model_dump()
        # RunSpec.security: each vehicle's verification outcomes (ok, or a rejection reason) by count
        report["security_outcomes"] = (None if self.spec.security is None else
                                       {v.name: dict(sorted(v.security.verifier.counts.items())) for v in self.vehicles})
        if self.spec.cpm_rules:
            report["rsu_lists"] = self.rsu_lists_sent()
        end_ns = self.start_ns + round(self.duration_s * 1e9)
        for v in self.vehicles if self.v2v is not None else ():
            report["vehicles"][v.name]["peers"] = v.obu.peers.summary(end_ns)
            report["vehicles"][v.name]["v2v_rejected"] = {k: n for k, n in v.obu.rejected.items() if k.startswith("v2v_")}
        return report

    # --- RSU side ----------------------------------------------------------------------
    def _rsu_capture(self, rsu: _Rsu) -> None:
        if not self._up("rsu"):
            return
        frame = rsu.camera.capture(self.clock.t_ns)
        self.perception[rsu.cfg.id].add_frame(frame)
        self.queue.at(frame.ready_true_ns, self._rsu_publish, rsu, frame)

    def _rsu_publish(self, rsu: _Rsu, frame: Frame) -> None:
        if not self._up("rsu"):
            return
        capture = Stamp(rsu.clock.local_from_true(frame.capture_true_ns), frame.capture_true_ns)
        msg = rsu.pipeline.on_frame(frame.detections, capture, self._rsu_now(rsu))
        self._broadcast_list(rsu, msg)
        predictions = rsu.pipeline.predictions(self._rsu_now(rsu))
        data = sign(encode(predictions), rsu.signer, predictions.header.publish_time_ns, rsu.predictions_key)
        self._broadcast(rsu, data, self._obu_predictions)
        if rsu.pipeline.config.predict_ahead:
            self.queue.at(self.clock.t_ns + rsu.camera.upsample_offset_ns, self._rsu_upsample, rsu)

    def _rsu_upsample(self, rsu: _Rsu) -> None:
        if not self._up("rsu"):
            return
        self._broadcast_list(rsu, rsu.pipeline.upsampled(self._rsu_now(rsu)))

    def _broadcast_list(self, rsu: _Rsu, msg: ObjectList) -> None:
        """An object list in the run's encoding (``spec.wire``: v2i, cpm or sdsm; an SDSM has none for no objects)."""
        # --cpm-rules: the rules' CPMs (none, one or segments) at the generation event's (monotonic) time
        for data in rsu.cpm.messages(msg, self.clock.t_ns) if rsu.cpm else [self._encode_list(msg)]:
            if data is None:
                continue
            self.list_bytes.append(len(data))
            if self.wire_files:
                self.wire_files[rsu.cfg.id].save(data)  # as sent, before any signature
            self._broadcast(rsu, sign(data, rsu.signer, msg.header.publish_time_ns, rsu.list_key), self._obu_receive)

    def _encode_list(self, msg: ObjectList) -> bytes | None:
        return encode_list(msg, self.spec.wire, self._origin)

    @property
    def _origin(self) -> tuple[float, float]:
        """The site's WGS84 origin (lat, lon degrees): a CPM's reference position, where the OBU places it."""
        return self.site_config.origin.lat_deg, self.site_config.origin.lon_deg

    def rsu_lists_sent(self) -> dict:
        """What the RSUs sent as object lists: messages, bytes (in all and per second of the run) and, with
        --cpm-rules, the objects the rules included by rule, CPMs segmented and generation events by outcome."""
        senders = [r.cpm for r in self.rsus if r.cpm is not None]
        total = sum(self.list_bytes)
        out = {"messages": len(self.list_bytes), "bytes": total, "bytes_per_s": round(total / self.duration_s, 1)}
        if senders:
            by_rule = sum((s.inclusion.included_by for s in senders), Counter())
            out.update(objects=sum(by_rule.values()), included_by=dict(sorted(by_rule.items())),
                       segmented=sum(s.segmented for s in senders), overflow=sum(s.overflow for s in senders),
                       events=dict(sorted(sum((s.inclusion.events for s in senders), Counter()).items())))
        return out

    def _rsu_now(self, rsu: _Rsu) -> Stamp:
        """Now on the RSU's wall clock (offset, drift, steps) and its monotonic clock (the true one)."""
        return Stamp(rsu.clock.now_ns(), self.clock.t_ns)

    def _rsu_time_query(self, vehicle: _Vehicle, rsu: _Rsu, data: bytes) -> None:
        if not self._up("rsu"):
            return
        request = self._memo.decoded(data, TimeRequest, lambda: decode(data, TimeRequest))  # one per broadcast
        if not rsu.answers.first(request):  # (the link duplicated the query)
            return
        t2 = rsu.clock.now_ns()
        reply = answer_time_request(request, rsu.pipeline.config.rsu_id, t2, t2 + RSU_REPLY_NS)
        data = sign(encode(reply), rsu.signer, reply.t3_ns, rsu.time_key)
        self.queue.at(self.clock.t_ns + RSU_REPLY_NS, self._send, vehicle, rsu, "downlink", data, self._obu_time_reply)

    # --- link --------------------------------------------------------------------------
    def _broadcast(self, rsu: _Rsu, data: bytes, deliver: Callable) -> None:
        """One RSU message down every vehicle's channel to that RSU, each its own draws."""
        for vehicle in self.vehicles:
            self._send(vehicle, rsu, "downlink", data, deliver)

    def _send(self, vehicle: _Vehicle, rsu: _Rsu, direction: str, data: bytes, deliver: Callable) -> None:
        """Through the pair's channel model at the current vehicle-RSU distance; duplicates arrive twice."""
        windows = self._down["link"]
        if windows and not self._up("link"):
            return
        channel = getattr(vehicle.links[rsu.index], direction)
        (x, y), (rsu_x, rsu_y) = self._ego_xy(vehicle), rsu.xy
        distance_m = float(np.hypot(x - rsu_x, y - rsu_y))
        # through _arrive (lost if the emulator dies meanwhile) only when the link has down windows
        event = (self._arrive, deliver, vehicle, rsu, data) if windows else (deliver, vehicle, rsu, data)
        for arrival_ns in channel.transmit_all(self.clock.t_ns, len(data), distance_m=distance_m):
            self.queue.at(arrival_ns, *event)

    def _ego_xy(self, vehicle: _Vehicle) -> tuple[float, float]:
        """The vehicle's true position (map, m) now; kept for the instant (a broadcast asks for it
        once per channel, and the true trajectory is a pure function of time)."""
        cached = self._ego_now.get(vehicle.name)
        if cached is None or cached[0] != self.clock.t_ns:
            xy = vehicle.world.ego_xy_at((self.clock.t_ns - self.start_ns) * 1e-9)  # ego_at's x, y, no Pose2D
            cached = self._ego_now[vehicle.name] = (self.clock.t_ns, xy)
        return cached[1]

    def _arrive(self, deliver: Callable, vehicle: _Vehicle, rsu: _Rsu, data: bytes) -> None:
        """A message in flight is lost when the emulator relaying it was killed meanwhile."""
        if self._up("link"):
            deliver(vehicle, rsu, data)

    # --- OBU side ----------------------------------------------------------------------
    def _obu_receive(self, vehicle: _Vehicle, rsu: _Rsu, data: bytes) -> None:
        """An RSU object list through the vehicle's inbox; then the cycle fuses if it was waiting for it."""
        kind = "rsu" if self.spec.wire == "v2i" else self.spec.wire  # the inbox's kinds (obu_service.inbox)
        outcome = vehicle.inbox.take(kind, rsu.list_key, data, self.clock.t_ns)
        if outcome is Outcome.DROPPED:
            return
        if outcome is Outcome.READ:
            vehicle.record.rsu_messages += 1
        self._obu_fuse_if_ready(vehicle)

    def _obu_predictions(self, vehicle: _Vehicle, rsu: _Rsu, data: bytes) -> None:
        vehicle.inbox.take("predictions", rsu.predictions_key, data, self.clock.t_ns)

    def _obu_sync(self, vehicle: _Vehicle) -> None:
        """One time request, up the vehicle's channel to every RSU (each answers it), and one to every peer."""
        data = encode(vehicle.obu.make_time_request(self.clock.t_ns))
        for rsu in self.rsus:
            self._send(vehicle, rsu, "uplink", data, self._rsu_time_query)
        if self.v2v is not None:
            self._v2v_broadcast(vehicle, encode(vehicle.obu.peers.make_time_request(self.clock.t_ns)),
                                self._peer_time_request)

    def _obu_time_reply(self, vehicle: _Vehicle, rsu: _Rsu, data: bytes) -> None:
        vehicle.inbox.take("time", rsu.time_key, data, self.clock.t_ns)

    def _obu_capture(self, vehicle: _Vehicle) -> None:
        frame = vehicle.sensing.capture(self.clock.t_ns)
        # the vehicle-only baseline gets every own frame, whatever the OBU does with it (truth derived at capture)
        vehicle.record.add_own_frame(frame, vehicle.sensing.lidar.last_truth, self.site_config)
        vehicle.obu.on_pose(frame.capture_ns, frame.pose)
        self.queue.at(frame.capture_ns + round(self.obu_config.fuse_delay_ms * 1e6), self._obu_fuse, vehicle, frame)

    def _obu_fuse(self, vehicle: _Vehicle, frame: OwnFrame) -> None:
        """Own objects are ready: plan the cycle; fuse now, on the awaited frame or at fuse_by."""
        fuse_by_ns = vehicle.obu.on_detections(frame.detections, frame.capture_ns)
        self.queue.at(fuse_by_ns, self._obu_fuse_if_ready, vehicle)
        self._obu_fuse_if_ready(vehicle)

    def _obu_fuse_if_ready(self, vehicle: _Vehicle) -> None:
        obu = vehicle.obu
        if not obu.ready(self.clock.t_ns):
            return
        out = obu.fuse(self.clock.t_ns)
        vehicle.record.add_output(out, obu.last_planning, vehicle.sensing.lidar.last_truth)  # truth derived at capture
        if self.link_series:  # what the live OBU publishes after each cycle
            vehicle.record.links.add(self.clock.t_ns, obu.metrics(self.clock.t_ns).rsus)
        if self.v2v is not None:
            self._v2v_broadcast(vehicle, encode(shared_list(out)), self._peer_list)
        self._record_clocks(vehicle, out)

    def _record_clocks(self, vehicle: _Vehicle, out: FusedObjectList) -> None:
        """Every synced RSU's clock estimate now (as the live OBU's metrics carry them), and the estimate at
        the cycle time of each RSU whose data the cycle used (``ObuPipeline.last_rsu_inputs``)."""
        obu, record = vehicle.obu, vehicle.record
        for rsu in self.rsus:
            rsu_id = rsu.cfg.id
            est, naive = obu.clock_offset(rsu_id, self.clock.t_ns), obu.naive_clock_offset(rsu_id)
            if est is not None:
                record.add_offset_sample(self.clock.t_ns, est.offset_ns, naive.offset_ns, est.drift_ppm, rsu_id)
        for rsu_id in obu.last_rsu_inputs:  # intra / inter: lists fused; planning: paths placed
            est = obu.clock_offset(rsu_id, out.cycle_time_ns)
            if est is not None:
                record.add_used_clock(out.cycle_time_ns, rsu_id, est.offset_at_ns(out.cycle_time_ns),
                                      planned=out.mode == "planning")

    # --- V2V ---------------------------------------------------------------------------
    def _v2v_broadcast(self, sender: _Vehicle, data: bytes, deliver: Callable) -> None:
        for receiver in self.vehicles:
            if receiver is not sender:
                self._v2v_send(sender, receiver, data, deliver)

    def _v2v_send(self, sender: _Vehicle, receiver: _Vehicle, data: bytes, deliver: Callable) -> None:
        """Through the (sender, receiver) channel at their distance now; duplicates arrive twice."""
        (ax, ay), (bx, by) = self._ego_xy(sender), self._ego_xy(receiver)
        channel = self.v2v_links[(sender.name, receiver.name)].downlink
        for arrival_ns in channel.transmit_all(self.clock.t_ns, len(data), distance_m=float(np.hypot(ax - bx, ay - by))):
            self.queue.at(arrival_ns, deliver, sender, receiver, data)

    def _peer_list(self, sender: _Vehicle, receiver: _Vehicle, data: bytes) -> None:
        try:
            msg = self._memo.decoded(data, FusedObjectList, lambda: decode(data, FusedObjectList))
            receiver.obu.peers.on_list(msg, sender.name, self.clock.t_ns)
        except CodecError as exc:
            receiver.obu.reject(f"v2v_{exc.reason}")

    def _peer_time_request(self, sender: _Vehicle, receiver: _Vehicle, data: bytes) -> None:
        """The receiver answers PEER_REPLY_NS later, back through its own channel to the sender."""
        t2_ns = self.clock.t_ns
        request = self._memo.decoded(data, TimeRequest, lambda: decode(data, TimeRequest))  # one per broadcast
        reply = receiver.obu.peers.answer(request, sender.name, t2_ns, t2_ns + PEER_REPLY_NS)
        if reply is not None:
            self.queue.at(t2_ns + PEER_REPLY_NS, self._v2v_send, receiver, sender, encode(reply), self._peer_time_reply)

    def _peer_time_reply(self, answerer: _Vehicle, receiver: _Vehicle, data: bytes) -> None:
        receiver.obu.peers.on_time_reply(decode(data, TimeReply), answerer.name, self.clock.t_ns)


def v2v_config(scenario_v2v: V2vConfig | None, switch: bool | None) -> V2vConfig | None:
    """The V2V a run uses: the scenario's (``switch`` None), none (False), the scenario's or the default (True)."""
    if switch is None:
        return scenario_v2v
    return (scenario_v2v or V2vConfig()) if switch else None
