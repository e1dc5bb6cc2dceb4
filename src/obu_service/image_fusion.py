"""The OBU's image-level fusion (``v2i obu --fusion roif``; Maqsud's ROIF thesis), pure: pairing, ROIF, output.

Driven by calls, never by a clock or Zenoh (the node, ``image_fusion_node``, feeds it). All
times are OBU-clock ns unless named ``*_rsu_ns``.

- Clock: NTP-style exchanges with each registered RSU (``TimeRequests``, ``ClockSync``, as the
  object pipeline), so an RSU frame's capture time t_rsu becomes t_obu = t_rsu - theta(t).
- RSU frames (``RsuImageFeatures``) are admitted or refused by counted reason: from an RSU
  outside the registry (``features_unknown_rsu``), before the clock is synchronised
  (``features_unsynced``), stamped after their arrival by more than ``future_tolerance_ms``
  (``features_future``), older than ``max_age_ms`` at arrival (``features_stale``), seen
  before (``features_duplicate``), too late for their frame (``features_late``, below). At
  most ``max_rsu_frames`` are kept (the newest).
- Own frames (``on_frame``: the ego camera's ``ViewFeatures`` at capture time t) wait for a
  partner: the newest RSU frame with |t_obu - t| <= ``pair_tolerance_ms``. A frame is fused
  as soon as its partner is buffered, else at t + ``wait_ms`` without one: its output is then
  its own boxes in the ego view (``view == "ego"``, counted in ``unpaired``). Frames are fused
  in capture order (the tracker's time runs forward). An RSU frame that arrives after the own
  frame it would have paired with went out alone is refused as ``features_late`` (the wait was
  too short for it): of the ``unpaired`` frames, about ``unpaired - features_late`` had an RSU
  frame that never came (lost on the link, skipped by the RSU).
- Each output is due at t + ``deadline_ms``; a later one is a deadline miss (counted, still
  published). ``metrics`` reports cycles, misses, refusals and the clock per RSU.
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

from v2i.fusion.box_tracker import BoxTrackerConfig
from v2i.fusion.roif import MAPPED_NONE, RoifConfig
from v2i.fusion.roif_features import ViewFeatures
from v2i.fusion.roif_pipeline import RoifFrame, RoifFramePipeline
from schemas.image_messages import (
    F4,
    I2,
    MAX_BOXES,
    U1,
    U4,
    BoxColumns,
    ImageFusedBoxes,
    RsuImageFeatures,
    to_bytes,
)
from schemas.messages import ObuMetrics, RsuLinkStatus, TimeReply, TimeRequest

from v2i.clock.clock_sync import ClockSync, OffsetEstimate
from v2i.clock.time_requests import TimeRequests

NS_PER_MS = 1_000_000
RECENT_FRAMES = 256  # (rsu id, seq, t_rsu) keys remembered for duplicates


@dataclass(frozen=True)
class ImageFusionConfig:
    vehicle_id: str = "ego"
    known_rsus: tuple[str, ...] = ()
    pair_tolerance_ms: float = 50.0  # |t_obu(RSU frame) - t(own frame)| a pair may differ by
    wait_ms: float = 300.0  # how long an own frame waits for its partner (RSU processing + link)
    deadline_ms: float = 450.0  # own capture -> output; later is a miss
    max_rsu_frames: int = 8
    max_age_ms: float = 2000.0  # an RSU frame older than this on arrival is stale
    future_tolerance_ms: float = 50.0  # beyond the clock uncertainty
    roif: RoifConfig = field(default_factory=RoifConfig)
    tracker: BoxTrackerConfig = field(default_factory=BoxTrackerConfig)


@dataclass(frozen=True)
class _RsuFrame:
    rsu_id: str
    seq: int
    t_rsu_ns: int
    t_obu_ns: int
    features: ViewFeatures


class ImageFusionPipeline:
    def __init__(self, config: ImageFusionConfig = ImageFusionConfig()):
        self.config = config
        self.roif = RoifFramePipeline(config.roif, config.tracker)
        self._requests = TimeRequests(config.vehicle_id)
        self._sync = {rsu_id: ClockSync() for rsu_id in config.known_rsus}
        self._rsu_frames: deque[_RsuFrame] = deque()
        self._seen: deque[tuple] = deque(maxlen=RECENT_FRAMES)
        self._pending: deque[tuple[int, ViewFeatures]] = deque()  # own frames (t_ns, features), oldest first
        self.rejected: Counter[str] = Counter()
        self.cycles = self.deadline_misses = self.unpaired = self.accepted = 0
        self._alone: deque[int] = deque(maxlen=RECENT_FRAMES)  # capture times (ns) of frames fused without a partner
        self._seq = 0

    # --- clock ------------------------------------------------------------------------------
    def make_time_request(self, t1_ns: int) -> TimeRequest:
        for sync in self._sync.values():  # a clock asked and not answered promptly is not trusted
            sync.note_request(t1_ns)
        return self._requests.make(t1_ns)

    def on_time_reply(self, reply: TimeReply, t4_ns: int) -> None:
        refused = self._requests.match(reply, t4_ns)
        if refused:
            self.reject(refused)
        for rsu_id, sample in self._requests.ripe(t4_ns):
            sync = self._sync.get(rsu_id)
            if sync is None:
                self.reject("time_reply_unknown_rsu")
            elif not sync.add(sample):
                self.reject("time_reply_outlier")

    def clock_offset(self, rsu_id: str, t_ns: int) -> OffsetEstimate | None:
        """Offset estimate (theta = rsu - obu) of one RSU at OBU time ``t_ns`` (None before any)."""
        sync = self._sync.get(rsu_id)
        return None if sync is None else sync.estimate_at(t_ns)

    def to_obu_ns(self, rsu_id: str, t_rsu_ns: int) -> int | None:
        sync = self._sync.get(rsu_id)
        return None if sync is None else sync.to_obu_ns(t_rsu_ns)

    # --- RSU frames -------------------------------------------------------------------------
    def reject(self, reason: str, count: int = 1) -> None:
        self.rejected[reason] += count

    def on_features(self, msg: RsuImageFeatures, receive_ns: int) -> bool:
        """Admit an RSU frame (True) or count why not (False)."""
        c = self.config
        key = (msg.rsu_id, msg.seq, msg.t_ns)
        if msg.rsu_id not in self._sync:
            return self._refuse("features_unknown_rsu")
        t_obu = self._sync[msg.rsu_id].to_obu_ns(msg.t_ns)
        if t_obu is None:
            return self._refuse("features_unsynced")
        if t_obu > receive_ns + c.future_tolerance_ms * NS_PER_MS:
            return self._refuse("features_future")
        if t_obu < receive_ns - c.max_age_ms * NS_PER_MS:
            return self._refuse("features_stale")
        if key in self._seen:
            return self._refuse("features_duplicate")
        self._seen.append(key)
        if any(abs(t_obu - t) <= c.pair_tolerance_ms * NS_PER_MS for t in self._alone):
            return self._refuse("features_late")
        self._rsu_frames.append(_RsuFrame(msg.rsu_id, msg.seq, msg.t_ns, t_obu, ViewFeatures.of_message(msg)))
        while len(self._rsu_frames) > c.max_rsu_frames:
            self._rsu_frames.popleft()
        self.accepted += 1
        return True

    def _refuse(self, reason: str) -> bool:
        self.reject(reason)
        return False

    # --- own frames -------------------------------------------------------------------------
    def on_frame(self, features: ViewFeatures, t_ns: int) -> int:
        """Queue an own camera frame captured at ``t_ns``; the time by which it is fused without a partner."""
        self._pending.append((int(t_ns), features))
        return int(t_ns + self.config.wait_ms * NS_PER_MS)

    def _partner(self, t_ns: int) -> _RsuFrame | None:
        tol = self.config.pair_tolerance_ms * NS_PER_MS
        near = [f for f in self._rsu_frames if abs(f.t_obu_ns - t_ns) <= tol]
        return max(near, key=lambda f: f.t_obu_ns) if near else None

    def ready(self, now_ns: int) -> bool:
        """Whether the oldest waiting frame can be fused now (its partner is here, or its wait is over)."""
        if not self._pending:
            return False
        t_ns = self._pending[0][0]
        return self._partner(t_ns) is not None or now_ns >= t_ns + self.config.wait_ms * NS_PER_MS

    def fuse_next(self, now_ns: int) -> ImageFusedBoxes:
        """Fuse the oldest waiting frame with its partner (if any) and account its deadline."""
        t_ns, obu = self._pending.popleft()
        partner = self._partner(t_ns)
        frame = self.roif.step(obu, None if partner is None else partner.features, t_ns * 1e-9)
        self.cycles += 1
        self.unpaired += partner is None
        if partner is None:
            self._alone.append(t_ns)
        publish_ns = max(int(now_ns), t_ns)
        self.deadline_misses += publish_ns > t_ns + self.config.deadline_ms * NS_PER_MS
        self._seq += 1
        return output_message(self.config.vehicle_id, self._seq, t_ns, publish_ns, frame, partner)

    # --- health -----------------------------------------------------------------------------
    def metrics(self, now_ns: int) -> ObuMetrics:
        paired = self.cycles - self.unpaired
        return ObuMetrics(
            vehicle_id=self.config.vehicle_id, t_ns=now_ns, cycles=self.cycles,
            output_deadline_misses=self.deadline_misses, rsu_deadline_misses=self.unpaired,
            covered_cycles=self.cycles, mode="roif", mode_counts={"roif": paired, "vehicle-only": self.unpaired},
            rsus=tuple(self._status(rsu_id, sync, now_ns) for rsu_id, sync in self._sync.items()),
            rejected=dict(self.rejected.most_common(64)))

    def _status(self, rsu_id: str, sync: ClockSync, now_ns: int) -> RsuLinkStatus:
        est = sync.estimate_at(now_ns)
        return RsuLinkStatus(rsu_id=rsu_id, clock_offset_ns=None if est is None else est.offset_ns,
                             clock_uncertainty_ns=None if est is None else est.uncertainty_ns,
                             sync_samples=0 if est is None else est.samples, sync_outliers=sync.outliers_rejected,
                             messages_accepted=self.accepted)


def output_message(vehicle_id: str, seq: int, t_ns: int, publish_ns: int, frame: RoifFrame,
                   partner: _RsuFrame | None) -> ImageFusedBoxes:
    """The ``ImageFusedBoxes`` of one stepped frame."""
    fused, obu, result = frame.fused, frame.obu, frame.result
    m = len(obu.boxes)
    if result is None:
        how, mapped, transform, err = np.zeros(m), np.full((m, 4), np.nan), np.full((m, 9), np.nan), np.full(m, np.nan)
        fit = {}
    else:
        how, mapped = result.mapping.how, result.mapped_obu_xyxy
        transform, err = result.mapping.transform.reshape(m, 9), result.mapping.inlier_error_px
        f = result.fit
        fit = dict(status=f.status, keypoints_obu=f.keypoints_obu, keypoints_rsu=f.keypoints_rsu, matches=f.matches,
                   inliers=f.inliers, frame_inlier_error_px=f.reprojection_px)
    rsu = {} if partner is None else dict(rsu_id=partner.rsu_id, rsu_seq=partner.seq, rsu_t_ns=partner.t_rsu_ns,
                                          rsu_t_obu_ns=partner.t_obu_ns, rsu=BoxColumns.of(*partner.features.detections))
    tracks = frame.tracks
    w, h = frame.image_wh
    keep_f = _rows(fused.xyxy, fused.scores)
    keep_t = _rows(tracks.xyxy, tracks.scores)
    return ImageFusedBoxes(
        vehicle_id=vehicle_id, seq=seq, t_ns=t_ns, publish_time_ns=publish_ns, view=frame.view,
        image_width=w, image_height=h, **rsu, **fit,
        fused=BoxColumns.of(fused.xyxy[keep_f], fused.scores[keep_f], fused.cls[keep_f]),
        fused_sources=to_bytes(fused.sources[keep_f], U1), fused_rsu_index=to_bytes(fused.rsu_index[keep_f], I2),
        fused_obu_index=to_bytes(fused.obu_index[keep_f], I2),
        tracks=BoxColumns.of(tracks.xyxy[keep_t], tracks.scores[keep_t], tracks.cls[keep_t]),
        track_ids=to_bytes(tracks.ids[keep_t], U4),
        obu=BoxColumns.of(*obu.detections), obu_mapping=to_bytes(np.where(how == MAPPED_NONE, 0, how), U1),
        obu_mapped=to_bytes(mapped, F4), obu_transform=to_bytes(transform, F4), obu_inlier_error_px=to_bytes(err, F4))


def _rows(xyxy: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Rows (in order) of boxes (N, 4) that fit the wire: finite and non-empty in float32, the
    ``MAX_BOXES`` highest scores at most (a coasting track's box may have shrunk to nothing)."""
    b = np.asarray(xyxy, float).reshape(-1, 4).astype(np.float32)
    ok = np.flatnonzero(np.isfinite(b).all(axis=1) & (b[:, 2] > b[:, 0]) & (b[:, 3] > b[:, 1]))
    if len(ok) > MAX_BOXES:
        ok = np.sort(ok[np.argsort(-np.asarray(scores)[ok], kind="stable")[:MAX_BOXES]])
    return ok
