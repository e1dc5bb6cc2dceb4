"""OBU node: the Zenoh shell around the OBU pipeline (``shell.ObuShell``, shared with the image-level node).

Zenoh callbacks only stamp the receive time and put the payload into a bounded,
rate-limited ``Intake`` (registered RSUs and the own sensors served first); the loop owns the
pipeline, wakes at each cycle's capture and fusion times and at each time-sync exchange,
and publishes every cycle whether or not RSU data arrived. An RSU message goes through the
inbox (``obu_service.inbox``): envelope and header first, and its objects only if the pipeline
admits the header.

With ``--source zenoh`` the vehicle's own detections and pose come from outside, on
``v2x/sensor/vehicle/{vehicle_id}/objects`` and ``.../pose`` (``schemas.sensor_messages``),
through the same intake; the loop screens them (``v2i.runtime.sensor_screen``, refusals counted as
``input_<reason>``) and feeds ``on_pose`` / ``on_detections`` exactly as the embedded vehicle
does. The cycle clock (``source.ExternalCycles``): one cycle per accepted detection frame, at
its capture time; when the next frame has not come by its slot's fuse-by time (expected
capture + deadline - compute margin), a gap cycle without own objects goes out on time
(counted as ``input_missing``); a frame whose slot already went out is ``input_late``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import ClassVar

from v2i.core.clock import Clock
from obu_service import KERNEL_MODULES
from v2i.core.jit import load_kernels
from v2i.core.objects import ObjectArray
from schemas import keys
from schemas.codec import CodecError, encode
from v2i.runtime.intake import Item
from v2i.runtime.process import log
from schemas import list_wire
from schemas.messages import EgoPose, ObuMetrics
from v2i.runtime.sensor_screen import InputRefused, SensorLimits, SensorScreen
from v2i.runtime.site import Site
from v2i.security.pki import start_warnings
from v2i.telemetry.latency import PeriodicSummary, StageLatency

from obu_service.config import ObuConfig
from obu_service.inbound_security import live_security
from obu_service.inbox import KINDS as INBOX_KINDS, Inbox
from obu_service.pipeline import ObuPipeline
from obu_service.shell import CRITICAL, Capture, Deadline, End, ObuShell, Sync
from obu_service.source import ExternalCycles, OwnFrame, OwnSensing, detections_of, pose_of
from obu_service.v2v_shell import KINDS as V2V_KINDS, V2vShell


INPUT_MAX_AGE_MS = 1000.0  # --source zenoh: older detection frames or poses are stale
CHEAP_INPUT_BYTES = 4096  # decodes in well under 1 ms (schema 4: ~180 objects, 0.1 ms; a prediction list's
# paths are still one model each: 64 objects x 128 points decode in ~5 ms)
# A CPM / SDSM (asn1tools, pure Python) decodes at ~1 us per byte: 8 objects 0.3 kB 0.3 ms, 255 objects 8 kB 8 ms
CHEAP_STANDARD_BYTES = 512


# --- the loop's timed events: small typed values, fired in due order; at one time by RANK (then as pushed);
# Deadline, Capture (--source sim: the vehicle's LiDAR and localisation sample), Sync and End: obu_service.shell
@dataclass(frozen=True)
class Fuse:
    """--source sim: the own objects of ``frame`` are ready (capture + fuse delay): its cycle starts."""

    frame: OwnFrame
    RANK: ClassVar[int] = 1


@dataclass(frozen=True)
class Gap:
    """--source zenoh: the fuse-by time ``slot_due_ns`` of the next slot; its cycle goes out without own
    objects unless a detection frame started it first."""

    slot_due_ns: int
    RANK: ClassVar[int] = 3


Event = Deadline | Fuse | Capture | Gap | Sync | End


class ObuNode(ObuShell):
    def __init__(self, config: ObuConfig, site: Site, sensing: Callable[[int], OwnSensing] | None = None,
                 clock: Clock | None = None):
        """Everything is loaded here; what depends on time zero (the vehicle's sampling, the cycle
        clock: ``_begin``) too, unless ``config.await_start``: then after the ready line.
        ``sensing(start_ns)``: the vehicle's own sensing run inside the OBU from time zero (``--source
        sim``); None: its detections and pose come over Zenoh (``--source zenoh``), and without
        ``config.duration_s`` it runs until stopped."""
        # the tracker's compiled loops load first (~0.3 s; compiled once per machine): not in a cycle, and
        # before the start time, whose first cycles would otherwise be late (the simulator's too where the
        # composition root imported it for simulated sensing)
        load_kernels(KERNEL_MODULES)
        if sensing is not None and config.duration_s is None:
            raise ValueError("own sensing runs for a set time: give duration_s (--duration)")
        pipeline = ObuPipeline(config.pipeline_config(site), config.lanes(site))
        known, vid = set(pipeline.config.known_rsus), config.vehicle_id
        own = {keys.sensor_vehicle_objects(vid), keys.sensor_vehicle_pose(vid)}
        super().__init__(config, clock, preferred=lambda key: key in own or keys.rsu_id_or_none(key) in known,
                         signed_kinds=frozenset(INBOX_KINDS))
        self._sensing = sensing
        self._lidar_rate_hz = site.vehicle(vid).lidar_rate_hz  # --source zenoh: the cycle rate
        self._origin = (site.origin.lat_deg, site.origin.lon_deg)  # where a CPM / SDSM is placed
        self.vehicle: OwnSensing | None = None  # --source sim, from _begin
        self.pipeline = pipeline
        self._security = live_security(config.pki_dir, config.security_policy, config.planning_max_age_s,
                                       self.pipeline.clock_offset, self.pipeline.reject, config.source_rate_hz,
                                       config.source_burst)
        for warning in [] if config.pki_dir is None else start_warnings(config.pki_dir, time.time_ns()):
            log(self.name, f"WARNING: {warning}")
        self._v2v = (V2vShell(vid, self.pipeline.enable_v2v(config.max_peers), self.clock, config.max_message_bytes)
                     if config.v2v else None)  # V2V peers (obu_service.v2v_shell)
        self._screen = SensorScreen(vid, "base_link", SensorLimits(config.max_objects_per_list, INPUT_MAX_AGE_MS,
                                                                  config.future_tolerance_ms, config.max_message_bytes))
        self._cycles: ExternalCycles | None = None  # --source zenoh, from _begin
        self._held: Item | None = None  # a large input held until after the next event
        self.latency = StageLatency()  # per-stage durations (v2i.telemetry.latency); read by other threads
        self._latency_summary = PeriodicSummary(self.latency)  # into the metrics, recomputed once a second
        self.last_metrics: ObuMetrics | None = None  # the latest published; one assignment, read by other threads
        self._begin_unless_awaited()

    def _begin(self, start_ns: int) -> None:
        """Time zero (OBU clock): the simulated vehicle samples from it (--source sim), or the cycle
        clock's first slot is it (--source zenoh)."""
        self.start_ns = start_ns
        if self._sensing is not None:
            self.vehicle = self._sensing(start_ns)
        else:
            pc = self.pipeline.config
            self._cycles = ExternalCycles(start_ns, round(1e9 / self._lidar_rate_hz),
                                          round((pc.deadline_ms - pc.compute_margin_ms) * 1e6))

    def _declare(self, session, entities: list) -> None:
        """The outputs (the planner-facing ones ``CRITICAL``) and the inputs: RSU lists in the subscribed
        wires, predictions, the own sensors with --source zenoh, the V2V keys with --v2v."""
        vid = self.config.vehicle_id
        self._pub = {name: session.declare_publisher(key, **(CRITICAL if name in ("objects", "planning") else {}))
                     for name, key in (("objects", keys.obu_objects(vid)), ("metrics", keys.obu_metrics(vid)),
                                       ("pose", keys.obu_pose(vid)), ("planning", keys.obu_planning(vid)))}
        entities += [*self._pub.values(),
                     session.declare_subscriber(keys.RSU_PREDICTIONS_ALL, self._on_predictions_sample)]
        if "v2i" in self.config.wires:
            entities.append(session.declare_subscriber(keys.RSU_OBJECTS_ALL, self._on_rsu_sample))
        # object lists in a standard encoding (RSU --wire cpm|sdsm), fused the same way; their ASN.1 is
        # compiled now: on a thread it held the GIL long enough to make the first cycles late
        for wire, key in (("cpm", keys.RSU_CPM_ALL), ("sdsm", keys.RSU_SDSM_ALL)):
            if wire in self.config.wires:
                list_wire.prepare(wire)
                entities.append(session.declare_subscriber(key, lambda sample, w=wire: self._put(w, sample)))
        if self._sensing is None:
            entities += [session.declare_subscriber(keys.sensor_vehicle_objects(vid),
                                                    lambda sample: self._put("sensor_objects", sample)),
                         session.declare_subscriber(keys.sensor_vehicle_pose(vid),
                                                    lambda sample: self._put("sensor_pose", sample))]
        if self._v2v is not None:
            entities += self._v2v.declare(session, self._put)

    def _stopped(self) -> str:
        p = self.pipeline
        return f"stopped: {p.cycles} cycles, {p.deadline_misses} deadline misses, rejected {dict(p.rejected)}"

    # --- Zenoh callbacks: stamp and enqueue only ---------------------------------------
    def _on_rsu_sample(self, sample) -> None:
        self._put("rsu", sample)

    def _on_predictions_sample(self, sample) -> None:
        self._put("predictions", sample)

    # --- the loop ------------------------------------------------------------------------
    def _schedule(self) -> None:
        now = self.clock.now_ns()
        if self.vehicle is None:
            self._at(self._cycles.gap_due_ns, Gap(self._cycles.gap_due_ns))
        for t in self.vehicle.cycle_times_ns(self.duration_s) if self.vehicle is not None else ():
            if t >= now:
                self._at(int(t), Capture())
        self._schedule_syncs(now)

    def _loop(self, stop: threading.Event) -> None:
        """Fire each event at its time; between events, handle inputs. A large input (over
        CHEAP_INPUT_BYTES, a CPM / SDSM over CHEAP_STANDARD_BYTES; an admitted one decodes in up
        to ~10 ms) is not started within ``input_guard_ms`` of the next event but held until
        after it: a cycle's output must not wait for it."""
        guard_s = self.config.input_guard_ms * 1e-3
        while not stop.is_set():
            due_ns, event = self._events.head()
            timeout_s = (due_ns - self.clock.now_ns()) * 1e-9
            if timeout_s > 0:
                item, self._held = self._held or self._intake.get(min(timeout_s, 0.2)), None
                cheap = CHEAP_STANDARD_BYTES if item is not None and item.kind in ("cpm", "sdsm") else CHEAP_INPUT_BYTES
                if item is not None and len(item.payload) > cheap and timeout_s < guard_s:
                    self._held = item
                    stop.wait(timeout_s)
                elif item is not None:
                    self._handle_input(item)
                continue
            self._events.pop()
            if isinstance(event, End):
                return
            self._fire(due_ns, event)

    def _fire(self, due_ns: int, event: Event) -> None:
        """One timed event, due at ``due_ns``."""
        match event:
            case Deadline():
                self._publish_if_ready()
            case Fuse(frame):
                self._start_cycle(frame.capture_ns, frame.detections)
            case Capture():
                self._capture(due_ns)
            case Gap(slot_due_ns):
                self._gap(slot_due_ns)
            case Sync():
                self._sync(due_ns)

    @cached_property
    def _inbox(self) -> Inbox:
        """The RSU messages' way in (``obu_service.inbox``): envelope, header, admission, body, pipeline."""
        return Inbox(self.pipeline, self._security, self.config.max_message_bytes, latency=self.latency,
                     ticks=time.perf_counter_ns, details=self._details, origin=self._origin)

    def _handle_input(self, item: Item) -> None:
        """One input off the intake. Stage ``queue`` (Zenoh callback -> taken here); an RSU message goes
        through the inbox (its stages ``verify``, ``decode``, ``ingest``, ``rsu_to_obu``)."""
        self.latency.observe_ns("queue", item.receive_ns, self.clock.now_ns())
        if item.kind in INBOX_KINDS:
            self._inbox.take(item.kind, item.source, item.payload, item.receive_ns)
            self._charge_if_unverified(item.source)
            self._publish_if_ready()
            return
        try:
            if item.kind.startswith("sensor_"):
                self._handle_sensor(item)
            elif item.kind in V2V_KINDS:
                self._v2v.handle(item)
        except CodecError as exc:  # InputRefused included
            self.pipeline.reject(exc.reason)
            self._details.setdefault(exc.reason, f"{item.kind} on {item.source}: {exc}")
        self._publish_if_ready()

    def _handle_sensor(self, item: Item) -> None:
        """--source zenoh: a pose goes to the pipeline (and out as the vehicle's pose); a detection
        frame starts a cycle, unless its slot already went out."""
        if item.kind == "sensor_pose":
            msg = self._screen.pose(item.payload, item.receive_ns)
            self._on_pose(msg.t_ns, pose_of(msg))
            return
        msg = self._screen.objects(item.payload, item.receive_ns)
        capture_ns = msg.header.capture_time_ns
        if not self._cycles.accept(capture_ns):
            raise InputRefused("input_late", f"frame captured at {capture_ns}: its cycle already went out")
        self._start_cycle(capture_ns, detections_of(msg))

    def _gap(self, slot_due_ns: int) -> None:
        """No detection frame by this slot's fuse-by time: the cycle goes out without own objects."""
        if slot_due_ns != self._cycles.gap_due_ns:
            return  # a frame started the slot's cycle meanwhile; its own gap event is queued
        capture_ns = self._cycles.gap(self.clock.now_ns())
        self.pipeline.reject("input_missing")
        self._start_cycle(capture_ns, ObjectArray.empty())

    def _on_pose(self, t_ns: int, pose) -> None:
        self.pipeline.on_pose(t_ns, pose)
        self._pub["pose"].put(encode(EgoPose(vehicle_id=self.config.vehicle_id, t_ns=t_ns, x=pose.x, y=pose.y,
                                             yaw=pose.yaw, vx=pose.vx, vy=pose.vy)))

    def _capture(self, due_ns: int) -> None:
        """--source sim: sample the vehicle (its pose out now); its objects are ready a fuse delay later."""
        frame = self.vehicle.capture(due_ns)
        self._on_pose(frame.capture_ns, frame.pose)
        self._at(frame.capture_ns + round(self.config.fuse_delay_ms * 1e6), Fuse(frame))

    def _start_cycle(self, capture_ns: int, detections: ObjectArray) -> None:
        """Own objects are ready: plan the cycle, then fuse now, on the awaited frame or at fuse_by."""
        if self.pipeline.pending:  # a cycle still waiting when the next starts: publish it first
            self._publish(self.clock.now_ns())
        fuse_by_ns = self.pipeline.on_detections(detections, capture_ns)
        self._at(fuse_by_ns, Deadline())
        if self.vehicle is None:  # --source zenoh: the next slot's gap cycle, unless a frame comes first
            self._at(self._cycles.gap_due_ns, Gap(self._cycles.gap_due_ns))
        self._publish_if_ready()

    def _publish_if_ready(self) -> None:
        now_ns = self.clock.now_ns()
        if self.pipeline.ready(now_ns):
            self._publish(now_ns)

    def _publish(self, now_ns: int) -> None:
        """Fuse and publish one cycle. Stages: ``fuse``, ``publish`` (encode and put of the fused list)."""
        t0_ns = time.perf_counter_ns()
        out = self.pipeline.fuse(now_ns)
        t1_ns = time.perf_counter_ns()
        self._count_crowded_out(out.mode_reason)
        self._pub["objects"].put(encode(out))
        self.latency.observe_ns("fuse", t0_ns, t1_ns)
        self.latency.observe_ns("publish", t1_ns, time.perf_counter_ns())
        if self._v2v is not None:
            self._v2v.share(out)
        if self.pipeline.last_planning is not None:
            self._pub["planning"].put(encode(self.pipeline.last_planning))
        self._count_refusals()
        metrics_ns = self.clock.now_ns()
        metrics = self.pipeline.metrics(metrics_ns, self._latency_summary.get(metrics_ns))
        self._pub["metrics"].put(encode(metrics))
        self.last_metrics = metrics
        self._trim.maybe()  # just published: the next deadline is a cycle away
        self._poll_trust()

    def _sync(self, due_ns: int) -> None:
        """Time requests out: to the RSUs (a Zenoh query; replies come through the intake) and the peers."""
        self._next_sync(due_ns)
        if self._v2v is not None:
            self._v2v.sync(self.clock.now_ns())
        self._query_time(self.pipeline.make_time_request(self.clock.now_ns()))
