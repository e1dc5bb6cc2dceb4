"""RSU node: the Zenoh shell around the RSU pipeline and its perception source.

Time queries are answered in the Zenoh callback (t2 and t3 must be stamped tightly), so
that callback is the RSU's attack surface: a query over ``max_query_bytes`` is refused
unread, queries beyond ``query_rate_hz`` (a token bucket over all queriers) are refused
before any decoding, and a querier (its ``obu_id``) beyond ``querier_rate_hz`` is refused
after it (``querier_rate_limited``), so a flood under one name does not starve the others;
each refusal is counted by reason in ``v2x/rsu/{id}/metrics`` and logged in a throttled
summary.

The node is configured by a ``v2i.runtime.site.Site`` (its RSU's position and frame rate) and is
handed its camera source (``rsu_service.source.RsuSource``) and clock model by the composition root
(``v2i.services``): it never sees a scenario. The RSU's perception is scored when its source knows
the truth (a simulated camera's frames carry what it could see).

With ``--source zenoh`` the RSU runs no camera of its own: it subscribes to
``v2x/sensor/rsu/{rsu_id}/objects`` (``SensorObjects`` in ``map``, stamped in this host's
clock), hands each payload from the Zenoh callback to a bounded, rate-limited ``Intake``, and
its loop screens it (``v2i.runtime.sensor_screen``: codec rules, sensor id, frame, stale, future,
out-of-order, object count; refusals counted as ``input_<reason>``) and processes the frame on
receipt exactly as a simulated camera's frame at its ready time.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable

import numpy as np

from v2i.perception.scoring import PerceptionTally
from schemas import keys
from v2i.core.clock import Clock, ClockModel, LocalClock, SystemClock, UnskewedClock
from rsu_service import KERNEL_MODULES
from v2i.core.jit import load_kernels
from v2i.fusion.wire import objects_from_states
from schemas.codec import CodecError, MalformedMessage, MessageTooLarge, decode, encode
from schemas.list_wire import encode_list, list_key, prepare
from v2i.runtime.intake import Intake, KeyedBuckets, TokenBucket
from schemas.image_messages import RsuImageFeatures
from schemas.messages import SOURCE_RSU, ObjectList, RsuMetrics, RsuPerception, TimeRequest
from v2i.runtime.process import MemoryTrim, ThrottledLog, announce, log, read_start_line, start_when_told
from v2i.runtime.sensor_screen import InputRefused, SensorLimits, SensorScreen
from v2i.runtime.site import Site
from v2i.runtime.transport import open_session
from v2i.runtime.wire_files import WireFiles
from v2i.security.envelope import Signer, sign
from v2i.security.pki import PkiError, load_signer, start_warnings
from v2i.telemetry.latency import PeriodicSummary, StageLatency

from rsu_service.config import RsuConfig
from rsu_service.cpm_segments import CpmSender
from rsu_service.pipeline import RsuPipeline, RsuPipelineConfig, Stamp, answer_time_request
from rsu_service.prediction import make_predictor
from rsu_service.source import Frame, RsuSource
from rsu_service.time_answers import TimeAnswers


MAX_QUERIERS = 1024  # querier buckets kept
REPORT_EVERY_NS = 1_000_000_000  # --source zenoh: metrics at least this often, frames or not
INPUT_QUEUE, INPUT_RATE_HZ, INPUT_BURST = 64, 50.0, 25  # --source zenoh: queued frames; frames/s and burst


class RsuNode:
    """Publishes object lists at the camera rate and answers time queries."""

    def __init__(self, config: RsuConfig, site: Site, source: RsuSource | None = None,
                 clock_model: ClockModel = UnskewedClock.of, true_clock: Clock | None = None):
        """Everything is loaded here; what depends on time zero (the RSU's clock from ``clock_model``,
        the source's capture times: ``_begin``) too, unless ``config.await_start``: then after the
        ready line. ``source`` None: the RSU's input comes over Zenoh (``--source zenoh``), and
        without ``config.duration_s`` it runs until stopped. A source (its renderer and detector
        loaded: seconds) gets its time zero from ``_begin``."""
        # the tracker's compiled loops first (~0.3 s; compiled once per machine): not in a frame; the simulator's
        # too where the composition root imported it for a simulated source
        load_kernels(KERNEL_MODULES)
        self.config = config
        self.name = f"rsu {config.rsu_id}"  # in its log lines
        self.true_clock = true_clock or SystemClock()
        self.start_ns: int | None = None  # time zero (true clock), from _begin
        self.clock: LocalClock | None = None  # the RSU's own clock (offset, drift, step from time zero), from _begin
        self._clock_model = clock_model
        self.duration_s = config.duration_s  # None: until stopped
        if source is not None and self.duration_s is None:
            raise ValueError("a camera source runs for a set time: give duration_s (--duration)")
        self.source = source
        self._inputs = Intake(INPUT_QUEUE, config.input_max_bytes, INPUT_RATE_HZ, INPUT_BURST)
        self._screen = SensorScreen(config.rsu_id, "map", SensorLimits(config.input_max_objects,
                                                                      config.input_max_age_ms,
                                                                      config.input_future_ms, config.input_max_bytes))
        self.pipeline = RsuPipeline(RsuPipelineConfig(rsu_id=config.rsu_id, sensor=f"camera/{config.source}",
                                                      predict_ahead=config.predict_ahead),
                                    make_predictor(config.predictor, site))
        self.rejected: Counter[str] = Counter()
        self.published = 0
        self.skipped = 0  # frames not published because their time had passed (restart, stall)
        self.time_replies = 0
        self._lock = threading.Lock()  # rejected, time_replies and the bucket: the query callback's
        self._queries = TokenBucket(config.query_rate_hz, config.query_burst, self.true_clock.now_ns())
        self._queriers = KeyedBuckets(config.querier_rate_hz, config.querier_burst, MAX_QUERIERS)  # by obu_id
        self._answers = TimeAnswers()
        self._log = ThrottledLog(self.name)
        self._trim = MemoryTrim()
        self._details: dict[str, str] = {}
        self._reported_ns = 0  # true clock of the last metrics
        self.latency = StageLatency()  # per-stage durations (v2i.telemetry.latency); read by other threads
        self._latency_summary = PeriodicSummary(self.latency)  # into the metrics, recomputed once a second
        self.last_metrics: RsuMetrics | None = None  # the latest published; one assignment, read by other threads
        # one signer per thread (loop, time-query callback): each decides when its certificate travels
        self._loop_signer, self._query_signer = _signer(config), _signer(config)
        for warning in [] if config.pki_dir is None else start_warnings(config.pki_dir, time.time_ns(),
                                                                         config.identity or config.rsu_id):
            log(self.name, f"WARNING: {warning}")
        # --save-wire: every list as sent (unsigned), one file each; an unwritable folder fails here, at start
        self._wire_files = (None if config.save_wire is None else
                            WireFiles(config.save_wire, config.rsu_id, config.wire, self.name))
        # --cpm-rules: the CPMs of each list under TS 103 324's generation rules, segmented to the MTU
        self._cpm = CpmSender(self._encode_list, config.cpm_mtu_bytes) if config.cpm_rules else None
        # scored when the source knows the truth (simulated world)
        rsu = site.rsu(config.rsu_id)
        self._origin = (site.origin.lat_deg, site.origin.lon_deg)  # a CPM / SDSM's reference position
        self.perception = PerceptionTally.of_source(self.source, rsu.xy)
        # predict-ahead publishes a frame's second list half a frame period after the first
        self._upsample_offset_ns = round(0.5e9 / rsu.rate_hz) if self.source is None else self.source.upsample_offset_ns
        if not config.await_start:
            self._begin(config.start_at_ns or self.true_clock.now_ns())

    def _begin(self, start_ns: int) -> None:
        """Time zero (true clock): the RSU's clock model and the source's capture times start from it."""
        self.start_ns = start_ns
        self.clock = self._clock_model(self.true_clock, start_ns)
        if self.source is not None:
            self.source.start_at(start_ns)

    def run(self, stop: threading.Event, await_start=read_start_line) -> None:
        """Declare, say ready, (``await_start``: wait for time zero, ``v2i.runtime.process.start_when_told``),
        then publish until the run's end or ``stop``."""
        prepare(self.config.wire)  # a CPM / SDSM's ASN.1 compiles now (~0.3 s), not on the first list
        session = open_session(self.config.listen, self.config.connect)
        entities = []
        try:
            rsu_id = self.config.rsu_id
            publisher = session.declare_publisher(list_key(self.config.wire, rsu_id))
            self._predictions = session.declare_publisher(keys.rsu_predictions(rsu_id))
            self._metrics = session.declare_publisher(keys.rsu_metrics(rsu_id))
            self._features = session.declare_publisher(keys.rsu_image_features(rsu_id))
            entities = [publisher, self._predictions, self._metrics, self._features,
                        session.declare_queryable(keys.rsu_time(rsu_id), self._on_time_query),
                        session.liveliness().declare_token(keys.rsu_alive(rsu_id))]
            if self.source is None:
                entities.append(session.declare_subscriber(keys.sensor_rsu_objects(rsu_id), self._on_input))
            announce("ready", "rsu", rsu_id=self.config.rsu_id, listen=self.config.listen)
            if self.start_ns is None and not start_when_told(self.name, stop, self._begin, self.true_clock.now_ns,
                                                             await_start):
                return
            (self._publish_inputs if self.source is None else self._publish_frames)(publisher, stop)
        finally:
            for entity in entities:
                entity.undeclare()
            session.close()
            self._log.flush(force=True)
            log(self.name, f"stopped: {self.published} object lists published, {self.skipped} past frames skipped, "
                       f"rejected {dict(self._refusals())}")
            if self._wire_files is not None:
                log(self.name, self._wire_files.summary())

    def _publish_frames(self, publisher, stop: threading.Event) -> None:
        """Capture, process and publish each frame at its time. Only what is current is
        published: a frame whose capture time is more than a frame period past (a restart
        mid-run, a stall) is skipped and counted, never sent late in a burst."""
        period_ns = round(1e9 / self.source.rate_hz)
        for capture_ns in self.source.capture_times_ns(self.duration_s):
            if not self._sleep_until(capture_ns, stop):
                return
            if self.true_clock.now_ns() - capture_ns > period_ns:
                self.skipped += 1
                continue
            frame = self.source.capture(int(capture_ns))
            if frame is None:  # the recording has ended
                break
            if not self._sleep_until(frame.ready_true_ns, stop) or not self._publish(publisher, frame, stop):
                return
        self._sleep_until(self.start_ns + round((self.duration_s + 1.0) * 1e9), stop)

    def _on_input(self, sample) -> None:
        """Zenoh callback (--source zenoh): stamp and enqueue only."""
        payload = sample.payload
        self._inputs.put("objects", str(sample.key_expr), len(payload), self.true_clock.now_ns(), payload.to_bytes)

    def _publish_inputs(self, publisher, stop: threading.Event) -> None:
        """--source zenoh: each frame received and accepted is processed and published at once,
        until the run's end (start + duration + 1 s; no duration: until stopped)."""
        end_ns = None if self.duration_s is None else self.start_ns + round((self.duration_s + 1.0) * 1e9)
        while not stop.is_set():
            remaining_ns = REPORT_EVERY_NS if end_ns is None else end_ns - self.true_clock.now_ns()
            if remaining_ns <= 0:
                return
            item = self._inputs.get(min(remaining_ns * 1e-9, 0.2))
            if self.true_clock.now_ns() - self._reported_ns > REPORT_EVERY_NS:  # refusals show while no frame comes
                self._report()
            if item is None:
                continue
            try:
                msg = self._screen.objects(item.payload, item.receive_ns)
            except InputRefused as exc:
                with self._lock:
                    self.rejected[exc.reason] += 1
                    self._details.setdefault(exc.reason, f"input on {item.source}: {exc}")
                continue
            dets = objects_from_states(msg.objects)
            dets = dets.with_(ids=np.full(len(dets), -1, dtype=np.int64), sources=np.full(len(dets), SOURCE_RSU))
            if not self._publish(publisher, Frame(msg.header.capture_time_ns, item.receive_ns, dets), stop):
                return

    def _publish(self, publisher, frame: Frame, stop: threading.Event) -> bool:
        """Process one frame whose detections are ready now and publish its list(s); False when
        stopped meanwhile. Stages: ``detect`` (capture -> detections ready), ``wake`` (ready ->
        processing starts), ``track``, then ``_put_list``'s."""
        start_ns = self.true_clock.now_ns()
        self.latency.observe_ns("detect", frame.capture_true_ns, frame.ready_true_ns)
        self.latency.observe_ns("wake", frame.ready_true_ns, start_ns)
        self.perception.add_frame(frame)
        capture = Stamp(self.clock.local_from_true(frame.capture_true_ns), frame.capture_true_ns)
        t0_ns = time.perf_counter_ns()
        self.pipeline.track(frame.detections, capture)
        self.latency.observe_ns("track", t0_ns, time.perf_counter_ns())
        self._put_list(publisher, self.pipeline.message)  # the publish stamp after tracking, right before encoding
        predictions = self.pipeline.predictions(self._now())
        self._predictions.put(sign(encode(predictions), self._loop_signer, predictions.header.publish_time_ns,
                                   str(self._predictions.key_expr)))
        if frame.image_features is not None:  # ROIF: the frame's boxes + ORB features, stamped at capture
            features = encode(RsuImageFeatures.from_view(self.config.rsu_id, self.published, capture.wall_ns,
                                                         frame.image_features))
            self._features.put(sign(features, self._loop_signer, self.clock.now_ns(), str(self._features.key_expr)))
        self.published += 1
        if self.config.predict_ahead and self._sleep_until(frame.ready_true_ns + self._upsample_offset_ns, stop):
            self._put_list(publisher, self.pipeline.upsampled)
            self.published += 1
        self._report()
        return not stop.is_set()

    def _put_list(self, publisher, message: Callable[[Stamp], ObjectList | None]) -> None:
        """Stamp the publish time, build the list (``message(stamp)``), encode it (--wire; an SDSM has
        none for an empty list; --cpm-rules: the rules' CPMs, none, one or segments), sign (--pki) and put
        each. Stages: ``message``, ``encode``, ``sign``, ``put``
        and ``stamp_to_put`` (the header's publish stamp -> put returned: the RSU's share of the OBU's
        one-way delay)."""
        stamp = self._now()
        t0_ns = time.perf_counter_ns()
        msg = message(stamp)
        t1_ns = time.perf_counter_ns()
        if msg is None:
            return
        # --cpm-rules: the CPMs the rules send (none, one, or segments), on the monotonic clock
        datas = self._cpm.messages(msg, stamp.mono_ns) if self._cpm is not None else [self._encode_list(msg)]
        t2_ns = time.perf_counter_ns()
        for unsigned in datas:
            if unsigned is None:
                return
            data = sign(unsigned, self._loop_signer, stamp.wall_ns, str(publisher.key_expr))
            t3_ns = time.perf_counter_ns()
            publisher.put(data)
            t4_ns = time.perf_counter_ns()
            self.latency.observe_ns("message", t0_ns, t1_ns)
            self.latency.observe_ns("encode", t1_ns, t2_ns)
            if self._loop_signer is not None:
                self.latency.observe_ns("sign", t2_ns, t3_ns)
            self.latency.observe_ns("put", t3_ns, t4_ns)
            self.latency.observe_ns("stamp_to_put", stamp.mono_ns, self.true_clock.now_ns())
            if self._wire_files is not None:  # after the put: the file never delays the list
                self._wire_files.save(unsigned)
            t2_ns = time.perf_counter_ns()

    def _encode_list(self, msg: ObjectList) -> bytes | None:
        """The wire bytes of one list in --wire (None: an SDSM has none for an empty list)."""
        return encode_list(msg, self.config.wire, self._origin)

    def _now(self) -> Stamp:
        """Now on the RSU's wall clock and on its monotonic clock (the simulation's true
        clock stands in for CLOCK_MONOTONIC: it never steps)."""
        true_ns = self.true_clock.now_ns()
        return Stamp(self.clock.local_from_true(true_ns), true_ns)

    def _sleep_until(self, true_ns: int, stop: threading.Event) -> bool:
        """Wait for a true-clock time; False when stopped first."""
        while not stop.is_set():
            remaining_s = (true_ns - self.true_clock.now_ns()) * 1e-9
            if remaining_s <= 0:
                return True
            stop.wait(remaining_s)
        return False

    def _refusals(self) -> Counter[str]:
        """Refused inputs by reason: time queries, and a recording's frames (``frame_<reason>``)."""
        with self._lock:
            for reason, n in self._inputs.take_counts().items():  # --source zenoh: refused unread
                self.rejected[f"input_{reason}"] += n
            rejected = Counter(self.rejected)
        frames = getattr(self.source, "frames", None)
        if frames is not None:
            rejected.update({f"frame_{reason}": n for reason, n in frames.refused.items()})
        return rejected

    def _report(self) -> None:
        """Publish the metrics; hand the refusals since the last report to the throttled log."""
        rejected = self._refusals()
        self._reported_ns = self.true_clock.now_ns()
        with self._lock:
            replies = self.time_replies
        self._log.totals(rejected, self._details)
        metrics = RsuMetrics(rsu_id=self.config.rsu_id, t_ns=self.clock.now_ns(), published=self.published,
                             skipped=self.skipped, time_replies=replies, rejected=dict(rejected),
                             perception=self._perception(), latency_ms=self._latency_summary.get(self._reported_ns))
        self._metrics.put(encode(metrics))
        self.last_metrics = metrics
        self._trim.maybe()

    def _perception(self) -> RsuPerception | None:
        return RsuPerception(**self.perception.scores()) if self.perception.frames else None

    def _on_time_query(self, query) -> None:
        # Answered in the callback: it reads only the clock and must stamp t2/t3 tightly.
        clock = self.clock
        if clock is None:  # before time zero (--await-start) there is no clock model to answer from
            return
        t2_ns = clock.now_ns()
        try:
            with self._lock:
                if not self._queries.take(self.true_clock.now_ns()):
                    raise _Refused("rate_limited")
            payload = query.payload
            if payload is None:
                raise MalformedMessage("time query without payload")
            if len(payload) > self.config.max_query_bytes:
                raise MessageTooLarge(f"time query of {len(payload)} bytes, limit {self.config.max_query_bytes}")
            request = decode(payload.to_bytes(), TimeRequest)
            with self._lock:
                if not self._queriers.take(request.obu_id, self.true_clock.now_ns()):
                    raise _Refused("querier_rate_limited")
                if not self._answers.first(request):  # one answer per query (rsu_service.time_answers)
                    raise _Refused("time_query_repeated")
        except (CodecError, _Refused) as exc:
            with self._lock:
                self.rejected[exc.reason] += 1
                self._details.setdefault(exc.reason, f"time query on {query.key_expr}: {exc}")
            return
        reply = answer_time_request(request, self.config.rsu_id, t2_ns, clock.now_ns())
        key = keys.rsu_time(self.config.rsu_id)
        query.reply(key, sign(encode(reply), self._query_signer, reply.t3_ns, key))
        with self._lock:
            self.time_replies += 1


def _signer(config: RsuConfig) -> Signer | None:
    """A signer as ``config.identity`` (default the RSU id) from ``config.pki_dir``; None without a PKI."""
    if config.pki_dir is None:
        return None
    try:
        return Signer(load_signer(config.pki_dir, config.identity or config.rsu_id))
    except PkiError as exc:
        raise ValueError(str(exc)) from None


class _Refused(Exception):
    """A time query refused before it was read; ``reason`` is a counter label."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason
