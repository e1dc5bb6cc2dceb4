"""RSU pipeline (pure): detections -> tracks -> timestamped object list.

Driven by calls with RSU-clock times; the node (live) and the offline runner feed it.
With ``predict_ahead`` (the track-predict compensation, seed 000 Algorithm 1) the RSU
publishes its tracks predicted to the publish time instead of the capture time, and
``upsampled(at_ns)`` gives the same tracks predicted further, so that a 5 Hz camera
yields 10 Hz object lists. The header's ``prediction_ns`` says how far ahead the
objects were predicted, so the vehicle measures the rest of the delay itself.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from fusion.motion import predict_ca, trajectories_cv
from fusion.objects import ObjectArray
from fusion.tracking import Tracker, TrackerConfig
from fusion.wire import states_from_objects
from schemas.messages import ObjectList, ObjectListHeader, PredictedPath, PredictionList, TimeReply, TimeRequest

# (objects (N), horizon_s, step_s) -> (N, K, 3) [x, y, yaw] at t0 + k step, k = 1..K
TrajectoryPredictor = Callable[[ObjectArray, float, float], np.ndarray]


@dataclass(frozen=True)
class RsuPipelineConfig:
    rsu_id: str = "rsu1"
    sensor: str = "camera"
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    predict_ahead: bool = False  # track-predict: publish tracks predicted to the publish time
    horizon_s: float = 5.0  # long-horizon trajectories for planning fusion (seed 003: ~5 s)
    path_step_s: float = 0.1


class RsuPipeline:
    """Tracks camera detections (map frame) and publishes confirmed tracks with velocity."""

    def __init__(self, config: RsuPipelineConfig = RsuPipelineConfig(), predictor: TrajectoryPredictor = trajectories_cv):
        self.config = config
        self.predictor = predictor
        self._tracker = Tracker(config.tracker)
        self._t_ref_ns: int | None = None
        self._seq = 0
        self._prediction_seq = 0  # predictions are numbered apart, so list seq gaps still mean loss
        self._last: tuple[int, ObjectArray] | None = None  # (capture_ns, confirmed tracks)

    def on_frame(self, dets: ObjectArray, capture_ns: int, publish_ns: int) -> ObjectList:
        """One processed camera frame: capture and publish times in the RSU clock (ns)."""
        if self._t_ref_ns is None:
            self._t_ref_ns = capture_ns
        tracks = self._tracker.step(dets, (capture_ns - self._t_ref_ns) * 1e-9)
        self._last = (capture_ns, tracks)
        ahead_ns = max(publish_ns - capture_ns, 0) if self.config.predict_ahead else 0
        return self._message(capture_ns, tracks, ahead_ns, publish_ns)

    def upsampled(self, publish_ns: int) -> ObjectList | None:
        """The last frame's tracks predicted to ``publish_ns`` (Algorithm 1's second pose)."""
        if self._last is None or not self.config.predict_ahead:
            return None
        capture_ns, tracks = self._last
        return self._message(capture_ns, tracks, max(publish_ns - capture_ns, 0), publish_ns)

    def predictions(self, publish_ns: int) -> PredictionList | None:
        """The last frame's tracks with their predicted paths over ``horizon_s`` (t0 = capture)."""
        if self._last is None:
            return None
        capture_ns, tracks = self._last
        paths = self.predictor(tracks, self.config.horizon_s, self.config.path_step_s)  # (N, K, 3)
        header = ObjectListHeader(rsu_id=self.config.rsu_id, seq=self._prediction_seq, capture_time_ns=capture_ns,
                                  publish_time_ns=max(publish_ns, capture_ns), sensor=self.config.sensor)
        self._prediction_seq += 1
        return PredictionList(
            header=header, step_ns=round(self.config.path_step_s * 1e9), objects=states_from_objects(tracks),
            paths=tuple(PredictedPath(id=int(i), x=p[:, 0].tolist(), y=p[:, 1].tolist(), yaw=p[:, 2].tolist())
                        for i, p in zip(tracks.ids, paths)),
        )

    def _message(self, capture_ns: int, tracks: ObjectArray, ahead_ns: int, publish_ns: int) -> ObjectList:
        # p(t + dt) = p + v dt + a dt^2 / 2 over the prediction horizon
        objs = predict_ca(tracks, ahead_ns * 1e-9) if ahead_ns else tracks
        header = ObjectListHeader(
            rsu_id=self.config.rsu_id, seq=self._seq, capture_time_ns=capture_ns, prediction_ns=ahead_ns,
            publish_time_ns=max(publish_ns, capture_ns), sensor=self.config.sensor,
        )
        self._seq += 1
        return ObjectList(header=header, objects=states_from_objects(objs))


def answer_time_request(request: TimeRequest, rsu_id: str, t2_ns: int, t3_ns: int) -> TimeReply:
    """NTP-style reply: t2 RSU receive, t3 RSU send (RSU clock), t1 echoed."""
    return TimeReply(rsu_id=rsu_id, seq=request.seq, t1_ns=request.t1_ns, t2_ns=t2_ns, t3_ns=t3_ns)
