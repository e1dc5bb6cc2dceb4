"""Perception sources of the RSU: what each camera frame yields, and when.

- ``SimulatedCamera`` (``--source sim``, the fast default): the scenario's noise model on
  ground truth.
- ``RenderedCamera`` (``--source camera``): the simulated world rendered by the RSU's camera
  (``v2i.sim.render``), through the ONNX detector and the calibrated ground homography.
- ``RecordedCamera`` (``--source video``): frames of a video file or an image folder (the
  user's own recording, model and calibration), through the same detector and homography.
- ``--source zenoh`` has no source object here: the node receives ``SensorObjects`` on
  ``v2x/sensor/rsu/{rsu_id}/objects`` (``rsu_service.node``), e.g. from ``v2i world``, which
  samples the ``SimulatedCamera`` below.

Frame k is captured at start + k / rate (true clock); its detections are ready after the
processing delay: the scenario's (80-120 ms by default, Bidare's KF poster) for the simulated world,
the measured detector time for a recording.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from v2i.core.objects import ObjectArray
from v2i.sim.seeding import stream
from v2i.sim.sensors import RsuCamera, frame_times
from v2i.sim.world import World

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


class _Schedule:
    """Capture times at ``rate_hz`` from ``start_ns`` (true clock)."""

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


class SimulatedCamera(_Schedule):
    """Camera + detector of one of the scenario's RSUs as a noise model on the simulated world
    (``world``: the site view, ``World(..., site=True)``, so that it sees every vehicle)."""

    def __init__(self, world: World, seed: int, start_ns: int, rsu_id: str = ""):
        """``rsu_id``: which RSU of the scenario (``Scenario.rsu_index``; "" the first)."""
        index = world.scenario.rsu_index(rsu_id) if rsu_id else 0
        cfg = world.scenario.rsus[index]
        self.world, self.start_ns = world, start_ns
        self.rate_hz = cfg.rate_hz
        self.camera = RsuCamera(cfg, stream(seed, "rsu_camera", index))

    def capture(self, capture_true_ns: int) -> Frame:
        dets, delay_s = self.camera.detect(self.world, (capture_true_ns - self.start_ns) * 1e-9)
        return Frame(int(capture_true_ns), int(capture_true_ns + round(delay_s * 1e9)), dets,
                     self.camera.last_visible_xy)


class RenderedCamera(_Schedule):
    """The RSU's camera rendering the simulated world, through detector and homography.

    The delay is the scenario's processing delay (the RSU's hardware, so that runs are
    reproducible); the detector's time on this machine is reported beside it.
    """

    def __init__(self, world: World, seed: int, start_ns: int, perception: ImagePerception,
                 rate_hz: float | None = None, features_max: int | None = None, rsu_id: str = ""):
        """``rate_hz``: frames per second (default the scenario's RSU rate); ``features_max``:
        with a number, each frame also carries ROIF features (at most that many ORB keypoints);
        ``rsu_id`` as for ``SimulatedCamera``."""
        from v2i.sim.camera import rsu_camera, rsu_sway
        from v2i.sim.render import SceneRenderer

        index = world.scenario.rsu_index(rsu_id) if rsu_id else 0
        cfg = world.scenario.rsus[index]
        self.world, self.start_ns, self.rate_hz = world, start_ns, rate_hz or cfg.rate_hz
        self.perception, self.features_max = perception, features_max
        # nominal pose (calibrated), wind
        self.camera, self.sway = rsu_camera(cfg), rsu_sway(cfg, stream(seed, "rsu_sway", index))
        self.renderer = SceneRenderer(world, seed)
        self.range_m, self.min_visible = cfg.range_m, cfg.min_visible_fraction  # what counts as seen (scoring)
        self._noise = stream(seed, "rsu_render", index)
        self._delay = stream(seed, "rsu_camera", index)
        self._delay_ms = cfg.processing_delay_ms

    def capture(self, capture_true_ns: int) -> Frame:
        t_s = (capture_true_ns - self.start_ns) * 1e-9
        rendered = self.renderer.render(self.sway.move(self.camera, t_s), t_s, self._noise)
        dets, detector_ms = self.perception.perceive(rendered.image)
        delay_s = self._delay.uniform(*self._delay_ms) / 1000.0
        return Frame(int(capture_true_ns), int(capture_true_ns + round(delay_s * 1e9)), dets,
                     self._visible_truth(rendered.labels, t_s), detector_ms,
                     _features(self.perception, rendered.image, self.features_max))

    def _visible_truth(self, labels, t_s: float) -> np.ndarray:
        """(T, 2) map centres of the bodies the frame shows well enough, within range."""
        seen = (labels.visible >= self.min_visible) & (labels.range_m <= self.range_m)
        return self.world.positions_of(labels.ids[seen], t_s)


class RecordedCamera(_Schedule):
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
                     _features(self.perception, image, self.features_max))


def _features(perception: ImagePerception, image, features_max: int | None):
    """ROIF features of the image just perceived (same render, same boxes), or None when not sent."""
    return None if features_max is None else perception.features(image, features_max)


def make_source(config, world: World, start_ns: int):
    """The source an ``RsuConfig`` names (``config.source``), its files opened and checked."""
    if config.source == "zenoh":
        raise ValueError("source zenoh has no local source: the RSU node subscribes to its sensor key")
    if config.source == "sim":
        return SimulatedCamera(world, config.seed, start_ns, config.rsu_id)
    perception = open_perception(config, world)
    features_max = config.image_features_max if config.image_features else None
    if config.source == "camera":
        return RenderedCamera(world, config.seed, start_ns, perception, config.rate_hz, features_max, config.rsu_id)
    if config.video is None:
        raise ValueError("--source video needs --video PATH (a video file or a folder of images)")
    from rsu_service.recording import ImageFrames  # (OpenCV: ~15 ms of every RSU's start, here only where a video is read)

    cal = v2i.perception.calibration
    return RecordedCamera(ImageFrames(config.video, (cal.width, cal.height)), perception, start_ns, config.rate_hz,
                          features_max)


def open_perception(config, world: World) -> ImagePerception:
    """Detector and calibration of an image source: the given files, else the shipped model and
    the scenario's shipped calibration."""
    from v2i.perception.calibration import calibration_path

    if config.calibration is not None:  # the user's camera: its own pose, no scenario range
        return ImagePerception.open(config.calibration, config.model, config.score_threshold,
                                    threads=config.detector_threads)
    path = calibration_path(config.scenario)
    if path is None:
        raise ValueError(f"scenario {config.scenario!r} has no shipped camera calibration: "
                         "pass --calibration FILE (make one with `v2i camera calibrate`)")
    rsu = world.scenario.rsus[world.scenario.rsu_index(config.rsu_id)]
    return ImagePerception.open(path, config.model, config.score_threshold, camera_xy=(rsu.position.x, rsu.position.y),
                                threads=config.detector_threads, max_range_m=rsu.range_m)
