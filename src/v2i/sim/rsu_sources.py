"""The RSU's simulated perception sources (``rsu_service.source.RsuSource``): the scenario's RSU
camera as a noise model on ground truth (``SimulatedCamera``, ``--source sim``) or rendering the
simulated world through the ONNX detector and the calibrated ground homography
(``RenderedCamera``, ``--source camera``; ``v2i.sim.render``); ``make_source`` picks the one an
``RsuConfig`` names. Both know the truth: each frame carries what the camera could see, so the
RSU's perception is scored.
"""

from __future__ import annotations

import numpy as np

from rsu_service.image_perception import ImagePerception
from rsu_service.source import Frame, Schedule, features_of, open_perception, video_source
from v2i.sim.scenario_site import site_of
from v2i.sim.seeding import stream
from v2i.sim.sensors import RsuCamera
from v2i.sim.world import World


class SimulatedCamera(Schedule):
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


class RenderedCamera(Schedule):
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
                     features_of(self.perception, rendered.image, self.features_max))

    def _visible_truth(self, labels, t_s: float) -> np.ndarray:
        """(T, 2) map centres of the bodies the frame shows well enough, within range."""
        seen = (labels.visible >= self.min_visible) & (labels.range_m <= self.range_m)
        return self.world.positions_of(labels.ids[seen], t_s)


def make_source(config, world: World, start_ns: int):
    """The source an ``RsuConfig`` names (``config.source``: sim, camera or video), its files opened
    and checked; an image source without ``config.calibration`` uses the scenario's shipped one."""
    if config.source == "zenoh":
        raise ValueError("source zenoh has no local source: the RSU node subscribes to its sensor key")
    if config.source == "sim":
        return SimulatedCamera(world, config.seed, start_ns, config.rsu_id)
    from v2i.perception.calibration import calibration_path

    site, shipped = site_of(world.scenario), calibration_path(config.scenario)
    if config.source == "video":
        return video_source(config, site, start_ns, shipped)
    features_max = config.image_features_max if config.image_features else None
    return RenderedCamera(world, config.seed, start_ns, open_perception(config, site, shipped), config.rate_hz,
                          features_max, config.rsu_id)
