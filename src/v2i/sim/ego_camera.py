"""The vehicle's simulated front camera for image-level fusion (``--fusion roif``; the OBU's
``obu_service.image_fusion_node.EgoCameraSource``): render, detect, ORB.

Frame k is captured at start + k / ``scenario.ego_camera.rate_hz`` (OBU clock, the true clock
in simulation): the scenario rendered (``v2i.sim.render.SceneRenderer``, textures by the run's seed,
as the RSU's renderer, so both cameras see the same surfaces) by ``v2i.sim.camera.vehicle_camera``
at the ego's pose, the ego itself hidden; boxes from the ONNX detector (the shipped model, or
``model_path``); ORB features inside them (``v2i.fusion.roif_features``). The same steps as
``v2i eval --fusion roif``'s ego view.
"""

from __future__ import annotations

import numpy as np

from v2i.fusion.roif import RoifConfig
from v2i.fusion.roif_features import ViewFeatures, view_features
from schemas.image_messages import MAX_BOXES
from v2i.core.clock import frame_times
from v2i.sim.seeding import stream
from v2i.sim.world import World


class EgoCamera:
    def __init__(self, world: World, seed: int, start_ns: int, model_path: str | None = None,
                 roif: RoifConfig | None = None, threads: int | None = None):
        from v2i.perception.detector import OnnxDetector
        from v2i.sim.camera import vehicle_camera
        from v2i.sim.render import SceneRenderer

        cfg = world.scenario.ego_camera
        if cfg is None:
            raise ValueError(f"scenario {world.scenario.name!r} has no ego_camera: --fusion roif needs one "
                             "(e.g. roif-intersection)")
        self.world, self.start_ns, self.rate_hz, self.config = world, start_ns, cfg.rate_hz, cfg
        self.roif = roif or RoifConfig()
        self.renderer = SceneRenderer(world, seed)
        self.detector = OnnxDetector(model_path, threads=threads)
        self._camera = vehicle_camera
        self._noise = stream(seed, "ego_render")
        # warm-up: the first render (its caches) and detection take ~140 ms against ~55 ms later; a
        # throwaway noise stream leaves the frames' draws as they were
        warm = self.renderer.render(self._camera(cfg, world.ego_at(0.0)), 0.0, np.random.default_rng(0), hide_ego=True)
        self._features(warm.image)

    def start_at(self, start_ns: int) -> None:
        """Set time zero (OBU clock): a node that waits for its start line (``--await-start``) builds
        the camera first (renderer, detector, warm-up: seconds) and sets it once, before the first frame."""
        self.start_ns = start_ns

    @property
    def period_ns(self) -> int:
        return round(1e9 / self.rate_hz)

    @property
    def image_size(self) -> tuple[int, int]:
        """Width, height (px) of its frames."""
        return self.config.image.width, self.config.image.height

    def frame_times_ns(self, duration_s: float) -> np.ndarray:
        """(K,) int64 capture times of the run."""
        return self.start_ns + np.round(frame_times(self.rate_hz, duration_s) * 1e9).astype(np.int64)

    def capture(self, t_ns: int) -> ViewFeatures:
        """The frame captured at ``t_ns``: its boxes (the ``MAX_BOXES`` best at most) and ORB features."""
        t_s = (t_ns - self.start_ns) * 1e-9
        frame = self.renderer.render(self._camera(self.config, self.world.ego_at(t_s)), t_s, self._noise, hide_ego=True)
        return self._features(frame.image)

    def _features(self, image: np.ndarray) -> ViewFeatures:
        """Detections (the ``MAX_BOXES`` best at most) and ORB features of one image (H, W, 3)."""
        d = self.detector.detect(image)
        xyxy, scores, cls = np.asarray(d.xyxy, float).reshape(-1, 4), np.asarray(d.scores, float), np.asarray(d.cls)
        keep = np.sort(np.argsort(-scores, kind="stable")[:MAX_BOXES])
        return view_features(image, (xyxy[keep], scores[keep], cls[keep]), self.roif)
