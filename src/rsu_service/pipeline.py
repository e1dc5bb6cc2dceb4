"""RSU pipeline (pure): detections -> tracks -> timestamped object list.

Driven by calls with RSU-clock times; the node (live) and the offline runner feed it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from fusion.objects import ObjectArray
from fusion.tracking import Tracker, TrackerConfig
from fusion.wire import states_from_objects
from schemas.messages import ObjectList, ObjectListHeader, TimeReply, TimeRequest


@dataclass(frozen=True)
class RsuPipelineConfig:
    rsu_id: str = "rsu1"
    sensor: str = "camera"
    tracker: TrackerConfig = field(default_factory=TrackerConfig)


class RsuPipeline:
    """Tracks camera detections (map frame) and publishes confirmed tracks with velocity."""

    def __init__(self, config: RsuPipelineConfig = RsuPipelineConfig()):
        self.config = config
        self._tracker = Tracker(config.tracker)
        self._t_ref_ns: int | None = None
        self._seq = 0

    def on_frame(self, dets: ObjectArray, capture_ns: int, publish_ns: int) -> ObjectList:
        """One processed camera frame: capture and publish times in the RSU clock (ns)."""
        if self._t_ref_ns is None:
            self._t_ref_ns = capture_ns
        tracks = self._tracker.step(dets, (capture_ns - self._t_ref_ns) * 1e-9)
        header = ObjectListHeader(
            rsu_id=self.config.rsu_id, seq=self._seq, capture_time_ns=capture_ns,
            publish_time_ns=max(publish_ns, capture_ns), sensor=self.config.sensor,
        )
        self._seq += 1
        return ObjectList(header=header, objects=states_from_objects(tracks))


def answer_time_request(request: TimeRequest, rsu_id: str, t2_ns: int, t3_ns: int) -> TimeReply:
    """NTP-style reply: t2 RSU receive, t3 RSU send (RSU clock), t1 echoed."""
    return TimeReply(rsu_id=rsu_id, seq=request.seq, t1_ns=request.t1_ns, t2_ns=t2_ns, t3_ns=t3_ns)
