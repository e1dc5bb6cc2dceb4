"""OBU node for image-level fusion (``v2i obu --fusion roif``): the Zenoh shell around
``image_fusion.ImageFusionPipeline`` and the ego camera (``shell.ObuShell``, shared with the object-level node).

Zenoh callbacks only stamp the receive time and put the payload into the bounded, rate-limited
``Intake`` (registered RSUs first): RSU feature frames (``v2x/rsu/*/image_features``) and time
replies. The one loop owns the pipeline: at each ego camera frame's capture time it renders,
detects and extracts features (its ``EgoCameraSource``: the simulator's ``v2i.sim.ego_camera``, handed
over by ``v2i.services``), queues the frame, and publishes every frame that
can be fused (``ImageFusedBoxes`` on ``v2x/obu/{id}/image_objects``) as soon as its RSU partner
is decoded or its wait is over. Every RSU message is verified before it is decoded, as in the
object-level node (``--pki``, ``--security``: ``inbound_security.InboundSecurity``; features
judged fresh in the RSU's clock through the offset estimate, time replies bound by their t1):
a drop is counted as ``security_<reason>``; a frame whose capture time is already a period past when the loop
gets to it (the loop fell behind) is not rendered but published at once as an empty ego-view
frame and counted (``camera_frame_skipped``), never silently dropped. Metrics
(``ObuMetrics``) follow every output.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np

from v2i.core.clock import Clock
from v2i.fusion.roif_features import ViewFeatures
from schemas import keys
from schemas.codec import CodecError, decode, encode
from schemas.image_messages import RsuImageFeatures
from v2i.runtime.intake import Item
from schemas.messages import TimeReply
from v2i.runtime.site import Site

from obu_service.config import ObuConfig
from obu_service.image_fusion import ImageFusionConfig, ImageFusionPipeline
from obu_service.inbound_security import live_security
from obu_service.shell import CRITICAL, Capture, Deadline, End, ObuShell, Sync

INPUTS_PER_LATE_EVENT = 8  # queued inputs taken before each overdue event (an RSU frame of 41 kB decodes in ~0.06 ms)

# the loop's timed events (obu_service.shell): Capture (the camera's frame), Deadline (a frame's wait for its RSU
# partner is over: it goes out without one), Sync, End
Event = Deadline | Capture | Sync | End


class EgoCameraSource(Protocol):
    """What the node needs of the vehicle's camera (the simulator's: ``v2i.sim.ego_camera``): its
    frame period, image size and capture times from time zero, and each frame's boxes and features."""

    @property
    def period_ns(self) -> int: ...

    @property
    def image_size(self) -> tuple[int, int]: ...

    def start_at(self, start_ns: int) -> None: ...

    def frame_times_ns(self, duration_s: float) -> np.ndarray: ...

    def capture(self, t_ns: int) -> ViewFeatures: ...


class ImageFusionNode(ObuShell):
    READY: ClassVar[dict] = {"fusion": "roif"}

    def __init__(self, config: ObuConfig, site: Site, camera: EgoCameraSource, clock: Clock | None = None):
        """``camera`` is loaded (renderer, detector); its time zero is set here, unless
        ``config.await_start``: then after the ready line (``_begin``). The run lasts ``config.duration_s``."""
        if config.duration_s is None:
            raise ValueError("image-level fusion runs for a set time: give duration_s (--duration)")
        known = tuple(config.registered_rsus(site))
        super().__init__(config, clock, preferred=lambda key: keys.rsu_id_or_none(key) in known,
                         signed_kinds=frozenset({"features", "time"}))
        self.camera = camera
        self.pipeline = ImageFusionPipeline(ImageFusionConfig(
            vehicle_id=config.vehicle_id, known_rsus=known, pair_tolerance_ms=config.roif_pair_tolerance_ms,
            wait_ms=config.roif_wait_ms, deadline_ms=config.roif_deadline_ms, max_age_ms=config.roif_max_age_ms,
            future_tolerance_ms=config.future_tolerance_ms))
        self._security = live_security(config.pki_dir, config.security_policy, config.roif_max_age_ms * 1e-3,
                                       self.pipeline.clock_offset, self.pipeline.reject, config.source_rate_hz,
                                       config.source_burst)
        self._begin_unless_awaited()

    def _begin(self, start_ns: int) -> None:
        """Time zero (OBU clock): the camera's frame k is captured at start + k / rate."""
        self.start_ns = start_ns
        self.camera.start_at(start_ns)

    def _declare(self, session, entities: list) -> None:
        """The image-level output (``CRITICAL``), the metrics, and the RSUs' image features in."""
        vid = self.config.vehicle_id
        self._out = session.declare_publisher(keys.obu_image_objects(vid), **CRITICAL)
        self._metrics = session.declare_publisher(keys.obu_metrics(vid))
        entities += [self._out, self._metrics,
                     session.declare_subscriber(keys.RSU_IMAGE_FEATURES_ALL, self._on_features_sample)]

    def _stopped(self) -> str:
        p = self.pipeline
        return (f"stopped: {p.cycles} image frames, {p.unpaired} without an RSU frame, "
                f"{p.deadline_misses} deadline misses, rejected {dict(p.rejected)}")

    # --- Zenoh callbacks: stamp and enqueue only ------------------------------------------
    def _on_features_sample(self, sample) -> None:
        self._put("features", sample)

    # --- the loop ---------------------------------------------------------------------------
    def _schedule(self) -> None:
        now = self.clock.now_ns()
        for t in self.camera.frame_times_ns(self.duration_s):
            if t >= now:
                self._at(int(t), Capture())
        self._schedule_syncs(now)

    def _loop(self, stop: threading.Event) -> None:
        """Fire each event at its time; between events, handle inputs. When the loop is behind (an
        event overdue: a capture takes most of a period on a loaded machine), it still takes up to
        ``INPUTS_PER_LATE_EVENT`` queued inputs before each overdue event: otherwise the RSU frames
        that complete the waiting ego frames would sit in the intake until every frame went out alone."""
        late_inputs = 0
        while not stop.is_set():
            due_ns, event = self._events.head()
            timeout_s = (due_ns - self.clock.now_ns()) * 1e-9
            if timeout_s > 0 or late_inputs < INPUTS_PER_LATE_EVENT:
                item = self._intake.get(min(max(timeout_s, 0.0), 0.2))
                if item is not None:
                    self._handle_input(item)
                    late_inputs += timeout_s <= 0
                    continue
                if timeout_s > 0:
                    continue
            self._events.pop()
            late_inputs = 0
            if isinstance(event, End):
                return
            self._fire(due_ns, event)
            self._publish_ready()

    def _fire(self, due_ns: int, event: Event) -> None:
        """One timed event, due at ``due_ns``; a Deadline needs nothing more: ``_publish_ready`` follows."""
        match event:
            case Capture():
                self._do_capture(due_ns)
            case Sync():
                self._do_sync(due_ns)

    def _handle_input(self, item: Item) -> None:
        max_bytes = self.config.max_message_bytes
        payload = self._security.open(item.payload, item.source, item.receive_ns, time_reply=item.kind == "time")
        self._charge_if_unverified(item.source)
        if payload is None:  # dropped unverified, counted as security_<reason>
            self._publish_ready()
            return
        try:
            if item.kind == "time":
                self.pipeline.on_time_reply(decode(payload, TimeReply, max_bytes), item.receive_ns)
            else:
                self.pipeline.on_features(decode(payload, RsuImageFeatures, max_bytes), item.receive_ns)
        except CodecError as exc:
            self.pipeline.reject(f"features_{exc.reason}" if item.kind == "features" else exc.reason)
            self._details.setdefault(exc.reason, f"{item.kind} on {item.source}: {exc}")
        self._publish_ready()

    def _do_capture(self, due_ns: int) -> None:
        if self.clock.now_ns() - due_ns > self.camera.period_ns:  # fell behind: this frame's time has passed
            self.pipeline.reject("camera_frame_skipped")
            features = ViewFeatures.of(np.zeros((0, 4)), [], [], np.zeros((0, 2)), np.zeros((0, 32)),
                                       self.camera.image_size)
        else:
            features = self.camera.capture(due_ns)
        fuse_by_ns = self.pipeline.on_frame(features, due_ns)
        self._at(fuse_by_ns, Deadline())

    def _publish_ready(self) -> None:
        while self.pipeline.ready(now_ns := self.clock.now_ns()):
            self._out.put(encode(self.pipeline.fuse_next(now_ns)))
            self._count_refusals()
            self._metrics.put(encode(self.pipeline.metrics(self.clock.now_ns())))
            self._trim.maybe()
            self._poll_trust()

    def _do_sync(self, due_ns: int) -> None:
        self._next_sync(due_ns)
        self._query_time(self.pipeline.make_time_request(self.clock.now_ns()))
