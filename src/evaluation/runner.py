"""Offline, deterministic driver: the live pipelines fed from an event queue.

The RSU pipeline, the OBU pipeline, the codec and the link channel model are the very
objects the services use; only the clock (simulated) and the transport (an event
queue instead of Zenoh) differ. A 30 s scenario runs in a few seconds.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable

import numpy as np

from link_emulator.channel import LinkModel
from link_emulator.control import apply_control
from link_emulator.profile import LinkProfile, load_profile
from obu_service.pipeline import ObuPipeline
from obu_service.source import OwnFrame, SimulatedVehicle
from perception.scoring import PerceptionTally
from rsu_service.pipeline import RsuPipeline, RsuPipelineConfig, Stamp, answer_time_request
from rsu_service.prediction import make_predictor
from rsu_service.source import Frame, make_source
from schemas.codec import CodecError, decode, encode
from schemas.messages import ObjectList, PredictionList, TimeReply, TimeRequest
from sim.clock import SimClock
from sim.scenario import load_scenario
from sim.world import World

from .chaos import SERVICES, ChaosTimeline
from .spec import EVAL_EPOCH_NS, RunRecord, RunSpec

RSU_REPLY_NS = 50_000  # RSU time between receiving a time query and answering it


class EventQueue:
    """Time-ordered callbacks; ties keep insertion order."""

    def __init__(self, clock: SimClock):
        self.clock = clock
        self._heap: list = []
        self._order = itertools.count()

    def at(self, t_ns: int, fn: Callable, *args) -> None:
        heapq.heappush(self._heap, (int(t_ns), next(self._order), fn, args))

    def run(self) -> None:
        while self._heap:
            t_ns, _, fn, args = heapq.heappop(self._heap)
            self.clock.t_ns = t_ns
            fn(*args)


class OfflineRun:
    """One scenario run; ``execute()`` returns the RunRecord scored by build_report."""

    def __init__(self, spec: RunSpec, start_ns: int = EVAL_EPOCH_NS, link_profile: LinkProfile | None = None,
                 chaos: ChaosTimeline | None = None):
        """``chaos``: timed faults; its RSU clock step must already be in ``spec`` (``with_chaos``)."""
        self.spec = spec
        self.chaos = chaos
        self.world = World(load_scenario(spec.scenario))
        self.duration_s = spec.duration_s or self.world.scenario.duration_s
        self.start_ns = start_ns
        self.clock = SimClock(start_ns)
        self.queue = EventQueue(self.clock)
        self.link = LinkModel(link_profile or load_profile(spec.profile), spec.seed)
        self.rsu_clock = spec.rsu_config().clock(self.clock, start_ns)
        self.rsu_config = spec.rsu_config()
        self.camera = make_source(self.rsu_config, self.world, start_ns)
        self.vehicle = SimulatedVehicle(self.world, spec.seed, start_ns)
        self.rsu = self._new_rsu()
        self.obu_config = spec.obu_config()
        self.obu = ObuPipeline(self.obu_config.pipeline_config(), self.obu_config.lanes())
        self.record = RunRecord(self.world, start_ns, self.duration_s)
        rsu = self.world.scenario.rsu.position
        self.record.perception = PerceptionTally.of_source(self.camera, (rsu.x, rsu.y))
        self._down = {name: self._windows_ns(name) for name in SERVICES}

    def _new_rsu(self) -> RsuPipeline:
        """A freshly started RSU (a restart loses its tracks and restarts its sequence numbers)."""
        return RsuPipeline(RsuPipelineConfig(rsu_id=self.world.scenario.rsu.id, predict_ahead=self.rsu_config.predict_ahead),
                           make_predictor(self.rsu_config.predictor, self.spec.scenario))

    def _windows_ns(self, service: str) -> list[tuple[int, int]]:
        if self.chaos is None:
            return []
        return [(self.start_ns + round(a * 1e9), self.start_ns + round(b * 1e9))
                for a, b in self.chaos.down_windows(service, self.duration_s + 1.0)]

    def _up(self, service: str, t_ns: int | None = None) -> bool:
        t_ns = self.clock.t_ns if t_ns is None else t_ns
        return not any(a <= t_ns < b for a, b in self._down[service])

    def _schedule_chaos(self) -> None:
        for event in self.chaos.sorted_events() if self.chaos else ():
            at_ns = self.start_ns + round(event.at_s * 1e9)
            control = event.link_control("eval")
            if control is not None:
                self.queue.at(at_ns, lambda c=control: apply_control(self.link, c, self.clock.t_ns))
            elif event.restart == "rsu":
                self.queue.at(at_ns, lambda: setattr(self, "rsu", self._new_rsu()))

    def execute(self) -> RunRecord:
        self._schedule_chaos()
        for t in self.camera.capture_times_ns(self.duration_s):
            self.queue.at(t, self._rsu_capture)
        cycles = self.vehicle.cycle_times_ns(self.duration_s)
        self.record.cycle_times_ns = cycles
        for t in cycles:
            self.queue.at(t, self._obu_capture)
        end_ns = self.start_ns + round(self.duration_s * 1e9)
        for t in range(self.start_ns, end_ns, round(1e9 / self.obu_config.sync_rate_hz)):
            self.queue.at(t, self._obu_sync)
        self.queue.run()
        self.record.covered_cycles = self.obu.covered_cycles
        self.record.rsu_deadline_misses = self.obu.rsu_deadline_misses
        return self.record

    # --- RSU side ----------------------------------------------------------------------
    def _rsu_capture(self) -> None:
        if not self._up("rsu"):
            return
        frame = self.camera.capture(self.clock.t_ns)
        self.record.perception.add_frame(frame)
        self.queue.at(frame.ready_true_ns, self._rsu_publish, frame)

    def _rsu_publish(self, frame: Frame) -> None:
        if not self._up("rsu"):
            return
        capture = Stamp(self.rsu_clock.local_from_true(frame.capture_true_ns), frame.capture_true_ns)
        msg = self.rsu.on_frame(frame.detections, capture, self._rsu_now())
        self._send(self.link.downlink, encode(msg), self._obu_receive)
        self._send(self.link.downlink, encode(self.rsu.predictions(self._rsu_now())), self._obu_predictions)
        if self.rsu.config.predict_ahead:
            self.queue.at(self.clock.t_ns + self.camera.upsample_offset_ns, self._rsu_upsample)

    def _rsu_upsample(self) -> None:
        if not self._up("rsu"):
            return
        self._send(self.link.downlink, encode(self.rsu.upsampled(self._rsu_now())), self._obu_receive)

    def _rsu_now(self) -> Stamp:
        """Now on the RSU's wall clock (offset, drift, steps) and its monotonic clock (the true one)."""
        return Stamp(self.rsu_clock.now_ns(), self.clock.t_ns)

    def _rsu_time_query(self, data: bytes) -> None:
        if not self._up("rsu"):
            return
        request = decode(data, TimeRequest)
        t2 = self.rsu_clock.now_ns()
        reply = answer_time_request(request, self.rsu.config.rsu_id, t2, t2 + RSU_REPLY_NS)
        self.queue.at(self.clock.t_ns + RSU_REPLY_NS, self._send, self.link.downlink, encode(reply), self._obu_time_reply)

    # --- link --------------------------------------------------------------------------
    def _send(self, channel, data: bytes, deliver: Callable) -> None:
        """Through the channel model at the current vehicle-RSU distance; duplicates arrive twice."""
        if not self._up("link"):
            return
        for arrival_ns in channel.transmit_all(self.clock.t_ns, len(data), distance_m=self._rsu_distance_m()):
            self.queue.at(arrival_ns, self._arrive, deliver, data)

    def _arrive(self, deliver: Callable, data: bytes) -> None:
        """A message in flight is lost when the emulator relaying it was killed meanwhile."""
        if self._up("link"):
            deliver(data)

    def _rsu_distance_m(self) -> float:
        ego = self.world.ego_at((self.clock.t_ns - self.start_ns) * 1e-9)
        rsu = self.world.scenario.rsu.position
        return float(np.hypot(ego.x - rsu.x, ego.y - rsu.y))

    # --- OBU side ----------------------------------------------------------------------
    def _obu_receive(self, data: bytes) -> None:
        try:
            self.obu.on_rsu_message(decode(data, ObjectList), self.clock.t_ns)
            self.record.rsu_messages += 1
        except CodecError as exc:
            self.obu.reject(exc.reason)
        self._obu_fuse_if_ready()

    def _obu_predictions(self, data: bytes) -> None:
        try:
            self.obu.on_predictions(decode(data, PredictionList), self.clock.t_ns)
        except CodecError as exc:
            self.obu.reject(exc.reason)

    def _obu_sync(self) -> None:
        self._send(self.link.uplink, encode(self.obu.make_time_request(self.clock.t_ns)), self._rsu_time_query)

    def _obu_time_reply(self, data: bytes) -> None:
        self.obu.on_time_reply(decode(data, TimeReply), self.clock.t_ns)

    def _obu_capture(self) -> None:
        frame = self.vehicle.capture(self.clock.t_ns)
        self.obu.on_pose(frame.capture_ns, frame.pose)
        self.queue.at(frame.capture_ns + round(self.obu_config.fuse_delay_ms * 1e6), self._obu_fuse, frame)

    def _obu_fuse(self, frame: OwnFrame) -> None:
        """Own objects are ready: plan the cycle; fuse now, on the awaited frame or at fuse_by."""
        fuse_by_ns = self.obu.on_detections(frame.detections, frame.capture_ns)
        self.queue.at(fuse_by_ns, self._obu_fuse_if_ready)
        self._obu_fuse_if_ready()

    def _obu_fuse_if_ready(self) -> None:
        if not self.obu.ready(self.clock.t_ns):
            return
        self.record.add_output(self.obu.fuse(self.clock.t_ns), self.obu.last_planning)
        rsu_id = self.rsu.config.rsu_id
        est, naive = self.obu.clock_offset(rsu_id, self.clock.t_ns), self.obu.naive_clock_offset(rsu_id)
        if est is not None:
            self.record.add_offset_sample(self.clock.t_ns, est.offset_ns, naive.offset_ns, est.drift_ppm)
