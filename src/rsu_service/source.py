"""Perception sources of the RSU: what each camera frame yields, and when.

The node is handed its source (``RsuSource``); which one is the composition root's choice
(``v2i.services``):

- ``RecordedCamera`` (``--source video``, here): frames of a video file or an image folder (the
  user's own recording, model and calibration), through the ONNX detector and the calibrated
  ground homography.
- the simulator's (``v2i.sim.rsu_sources``): ``SimulatedCamera`` (``--source sim``, the fast
  default: the scenario's noise model on ground truth) and ``RenderedCamera`` (``--source
  camera``: the simulated world rendered, through the same detector and homography).
- ``--source zenoh`` has no source object: the node receives ``SensorObjects`` on
  ``v2x/sensor/rsu/{rsu_id}/objects`` (``rsu_service.node``), e.g. from ``v2i world``, which
  samples the ``SimulatedCamera``.

Frame k is captured at start + k / rate (true clock); its detections are ready after the
processing delay: the scenario's (80-120 ms by default, Bidare's KF poster) for the simulated world,
the measured detector time for a recording.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from v2i.core.clock import frame_times
from v2i.core.objects import ObjectArray
from v2i.runtime.site import Site

from rsu_service.image_perception import ImagePerception

if TYPE_CHECKING:
    from rsu_service.recording import ImageFrames

SOURCES = ("sim", "camera", "video", "zenoh")


@dataclass(frozen=True)
class Frame:
    """One processed camera frame: detections (map frame) and its true-clock times."""

    capture_true_ns: int
    ready_true_ns: int  # capture + processing delay: when the detections exist
    detections: ObjectArray
    visible_truth_xy: np.ndarray | None = None  # (T, 2) m: the truth this frame could see (simulation only)
    detector_ms: float | None = None  # the detector's own time on this frame
    image_features: object | None = None  # v2i.fusion.roif_features.ViewFeatures when the RSU sends them (ROIF)


class RsuSource(Protocol):
    """What the RSU node needs of a camera source: its frame rate and capture times from time zero,
    and each frame (None: the source has ended). A source that knows the truth (a simulation)
    gives frames with ``visible_truth_xy``: the node scores its perception against it."""

    rate_hz: float

    @property
    def upsample_offset_ns(self) -> int: ...

    def start_at(self, start_ns: int) -> None: ...

    def capture_times_ns(self, duration_s: float) -> np.ndarray: ...

    def capture(self, capture_true_ns: int) -> Frame | None: ...


class Schedule:
    """Capture times at ``rate_hz`` from ``start_ns`` (true clock): the base of the cameras."""

    rate_hz: float
    start_ns: int

    @property
    def upsample_offset_ns(self) -> int:
        """Half a frame period: when the upsampled (second) list of a frame is published."""
        return round(0.5e9 / self.rate_hz)

    def start_at(self, start_ns: int) -> None:
        """Set time zero (true clock): a node that waits for its start line (``--await-start``) builds
        the source first (a renderer and detector take seconds) and sets it once, before the first capture."""
        self.start_ns = start_ns

    def capture_times_ns(self, duration_s: float) -> np.ndarray:
        """(K,) int64 true capture times within the run."""
        t_s = frame_times(self.rate_hz, duration_s)
        return self.start_ns + np.round(t_s * 1e9).astype(np.int64)


class RecordedCamera(Schedule):
    """Frames of a video file or image folder, one per capture time, in order: frame k is the one
    of capture time k (``start + k / rate``), also after the RSU let capture times pass unpublished
    (a stall: those frames are skipped unread, ``frames.skipped``), so that a stamp always names its
    frame's time.

    A frame that cannot be read (corrupt file, wrong size) yields no detections and is
    counted in ``frames.refused``; the run goes on. ``capture`` gives None at the end.
    """

    def __init__(self, frames: ImageFrames, perception: ImagePerception, start_ns: int, rate_hz: float | None = None,
                 features_max: int | None = None):
        self.frames, self.perception, self.start_ns = frames, perception, start_ns
        self.rate_hz = rate_hz or frames.fps
        self.features_max = features_max

    def capture_times_ns(self, duration_s: float) -> np.ndarray:
        times = super().capture_times_ns(duration_s)
        return times if self.frames.count is None else times[: self.frames.count]

    def capture(self, capture_true_ns: int) -> Frame | None:
        k = round((capture_true_ns - self.start_ns) * self.rate_hz * 1e-9)  # t_k = start + k / rate
        while self.frames.position < k and not self.frames.ended:
            self.frames.skip()
        image = None if self.frames.ended else self.frames.next()
        if self.frames.ended:
            return None
        if image is None:
            return Frame(int(capture_true_ns), int(capture_true_ns), ObjectArray.empty())
        dets, detector_ms = self.perception.perceive(image)
        return Frame(int(capture_true_ns), int(capture_true_ns + round(detector_ms * 1e6)), dets, None, detector_ms,
                     features_of(self.perception, image, self.features_max))


def features_of(perception: ImagePerception, image, features_max: int | None):
    """ROIF features of the image just perceived (same render, same boxes), or None when not sent."""
    return None if features_max is None else perception.features(image, features_max)


def video_source(config, site: Site, start_ns: int, shipped_calibration: Path | None = None) -> RecordedCamera:
    """``--source video``: the recording ``config.video`` names, opened and checked, through
    ``open_perception``."""
    if config.video is None:
        raise ValueError("--source video needs --video PATH (a video file or a folder of images)")
    perception = open_perception(config, site, shipped_calibration)
    features_max = config.image_features_max if config.image_features else None
    from rsu_service.recording import ImageFrames  # (OpenCV: ~15 ms of every RSU's start, here only where a video is read)

    cal = perception.calibration
    return RecordedCamera(ImageFrames(config.video, (cal.width, cal.height)), perception, start_ns, config.rate_hz,
                          features_max)


def open_perception(config, site: Site, shipped_calibration: Path | None = None) -> ImagePerception:
    """Detector and calibration of an image source: the calibration file ``config.calibration`` (the
    user's camera: its own pose, no range), else ``shipped_calibration`` (a scenario's: the camera at
    the site RSU's position, within its range), and ``config.model`` or the shipped model."""
    if config.calibration is not None:
        return ImagePerception.open(config.calibration, config.model, config.score_threshold,
                                    threads=config.detector_threads)
    if shipped_calibration is None:
        where = f"site {site.name!r}" if getattr(config, "site", None) else f"scenario {config.scenario!r}"
        raise ValueError(f"{where} has no shipped camera calibration: "
                         "pass --calibration FILE (make one with `v2i camera calibrate`)")
    rsu = site.rsu(config.rsu_id)
    return ImagePerception.open(shipped_calibration, config.model, config.score_threshold, camera_xy=rsu.xy,
                                threads=config.detector_threads, max_range_m=rsu.range_m)
