"""``v2i demo --fusion roif``: image-level fusion live (RSU camera + link + OBU as processes).

The RSU renders its camera (``--source camera``) at the ego camera's rate, detects, and sends
each frame's boxes + ORB features (``--image-features``); the link emulator relays them; the OBU
(``--fusion roif``) renders its own camera, pairs, fuses, tracks and publishes ``ImageFusedBoxes``
per frame. The demo keeps those messages (one per ego frame: ``duration x rate`` of them) and,
after the run, scores them with the offline eval's tally (``v2i.offline.image_fusion.score_frame``)
against truth labels it renders itself, so the OBU never sees truth:

- RSU view truth: the RSU camera (with its seeded wind sway, as the RSU renders it) at the
  paired RSU frame's true capture time (its clock-corrected time snapped to the RSU's frame
  grid, start + k / rate); for a frame without an RSU partner, at the ego frame's time (such a
  frame has no boxes in the RSU view: its truths count as missed);
- ego view truth: the ego camera at the ego frame's time.

The report's ``image_fusion`` has the offline eval's keys; ``image_fusion_live`` adds frames
expected / published / paired / unpaired, output latency and deadline misses, and the OBU's
refusals by reason (from its last ``ObuMetrics``).
"""

from __future__ import annotations

import numpy as np

from v2i.fusion.box_tracker import BoxTracks
from v2i.fusion.roif import BoxMapping, FusedBoxes, HomographyFit, RoifResult
from v2i.fusion.roif_features import ViewFeatures
from v2i.fusion.roif_pipeline import RoifFrame
from schemas import keys
from schemas.codec import decode
from schemas.image_messages import F4, I2, U1, U4, ImageFusedBoxes, column
from schemas.messages import ObuMetrics, RsuMetrics

from v2i.orchestration.children import READY_TIMEOUT_S
from v2i.orchestration.demo import Demo
from v2i.orchestration.inbox_scoring import startup_summary
from v2i.offline.image_fusion import FusionTally, score_frame
from v2i.orchestration.live_security import security_argv

PAIRED_KEYS = ("frames", "truths", "detection_accuracy", "rsu_only_detection_accuracy", "vehicle_only_detection_accuracy",
               "mean_iou", "precision")

class ImageFusionDemo(Demo):
    """The live ROIF demo: ``Demo``'s processes and supervision, its own flags, output and score."""

    def __init__(self, spec, ready_timeout_s: float = READY_TIMEOUT_S, pki_dir: str | None = None,
                 progress: str | None = None):
        """RSU and OBU build a renderer and load a detector before they say ready (seconds each on 2
        cores); the run starts when both have, within ``ready_timeout_s``."""
        super().__init__(spec, ready_timeout_s=ready_timeout_s, pki_dir=pki_dir, progress=progress)
        sc = self.world.scenario
        if sc.ego_camera is None:
            raise ValueError(f"scenario {sc.name!r} has no ego_camera: --fusion roif needs one (e.g. roif-intersection)")
        self.rate_hz = sc.ego_camera.rate_hz
        self.outputs: list[ImageFusedBoxes] = []
        self.obu_metrics: ObuMetrics | None = None

    def _rsu_id(self) -> str:
        return self.world.scenario.rsu.id

    def _argv(self, name: str) -> list[str]:
        """RSU and OBU argv for ROIF; one detector thread each (two processes render and detect at
        10 Hz on 2 cores: more threads only contend); the RSU signs its features and time replies and
        the OBU verifies them as in ``Demo`` (``live_security.security_argv``)."""
        argv = super()._argv(name)
        if name == "rsu":  # the camera source at the ego camera's rate, sending its features
            argv = argv[: argv.index("--source")] + ["--source", "camera", "--image-features", "--rsu-id",
                                                      self._rsu_id(), "--rate-hz", f"{self.rate_hz:g}",
                                                      "--detector-threads", "1",
                                                      *security_argv(self.spec, name, self.pki_dir)]
        elif name == "obu":
            argv = argv[: argv.index("--fusion")] + ["--fusion", "roif", "--roif-threads", "1",
                                                      *security_argv(self.spec, name, self.pki_dir)]
        return argv

    def _more_subscriptions(self, monitor, vehicle_id: str) -> list:
        return [monitor.declare_subscriber(keys.obu_image_objects(vehicle_id), lambda s: self._keep("image_objects", s))]

    def _score(self, kind: str, data: bytes) -> None:
        if kind == "image_objects":
            self.outputs.append(decode(data, ImageFusedBoxes))
        elif kind == "metrics":
            self.obu_metrics = decode(data, ObuMetrics)
        elif kind == "rsu_metrics":
            perception = decode(data, RsuMetrics).perception
            if perception is not None:
                self.record.rsu_perception = perception.model_dump()

    def _report(self) -> dict:
        start_ns = self.record.start_ns
        tally, paired = score_outputs(self.world, self.spec.seed, start_ns, self.rate_hz, self.outputs)
        expected = int(np.ceil(self.duration_s * self.rate_hz - 1e-9))
        m = self.obu_metrics
        latency_ms = [(o.publish_time_ns - o.t_ns) / 1e6 for o in self.outputs]
        live = {
            "frames_expected": expected, "frames_published": len(self.outputs),
            "frames_paired": sum(o.view == "rsu" for o in self.outputs),
            "frames_unpaired": sum(o.view == "ego" for o in self.outputs),
            "output_latency_ms": _percentiles(latency_ms),
            "paired_frames_only": {k: paired.section()[k] for k in PAIRED_KEYS},
            "cycles": None if m is None else m.cycles,
            "output_deadline_misses": None if m is None else m.output_deadline_misses,
            "rejected": {} if m is None else dict(m.rejected),
            "monitor_messages_dropped": dict(self.dropped),
        }
        return {"driver": "demo", "scenario": self.world.scenario.name, "fusion": "roif", "profile": self.spec.profile,
                "seed": self.spec.seed, "duration_s": self.duration_s, "detector": "onnx", "camera_rate_hz": self.rate_hz,
                "image_fusion": tally.section(), "image_fusion_live": live,
                "startup": startup_summary(self.ready_s, self._started.values())}


def score_outputs(world, seed: int, start_ns: int, rate_hz: float,
                  outputs: list[ImageFusedBoxes]) -> tuple[FusionTally, FusionTally]:
    """The offline eval's tally over the OBU's outputs, in frame order, against rendered truth
    labels; and the same over the frames that paired with an RSU frame only."""
    from v2i.sim.camera import rsu_camera, rsu_sway, vehicle_camera
    from v2i.sim.render import SceneRenderer
    from v2i.sim.seeding import stream

    sc = world.scenario
    renderer = SceneRenderer(world, seed)
    cam_rsu, sway = rsu_camera(sc.rsu), rsu_sway(sc.rsu, stream(seed, "rsu_sway"))
    period_ns = 1e9 / rate_hz
    tally, paired = FusionTally(), FusionTally()
    for msg in sorted(outputs, key=lambda o: o.t_ns):
        t_ego_s = (msg.t_ns - start_ns) * 1e-9
        t_rsu_ns = msg.t_ns if msg.rsu_t_obu_ns is None else msg.rsu_t_obu_ns
        t_rsu_s = round((t_rsu_ns - start_ns) / period_ns) / rate_hz  # the RSU's frame grid
        rsu_labels = renderer.render(sway.move(cam_rsu, t_rsu_s), t_rsu_s).labels
        ego_labels = renderer.render(vehicle_camera(sc.ego_camera, world.ego_at(t_ego_s)), t_ego_s, hide_ego=True).labels
        score_frame(tally, frame_of(msg), rsu_labels, ego_labels)
        if msg.view == "rsu":  # its own tracker view: the tracks are the same objects, scored again
            score_frame(paired, frame_of(msg), rsu_labels, ego_labels)
    return tally, paired


def frame_of(msg: ImageFusedBoxes) -> RoifFrame:
    """The ``RoifFrame`` an output message describes (no keypoints: the scorer reads boxes only)."""
    def view(boxes, wh) -> ViewFeatures:
        return ViewFeatures.of(*boxes.arrays(), np.zeros((0, 2)), np.zeros((0, 32)), wh, np.zeros(0))

    wh = (msg.image_width, msg.image_height)
    obu_wh = wh if msg.view == "ego" else (0, 0)  # the ego image's size is not on the wire; boxes suffice
    obu = view(msg.obu, obu_wh)
    xyxy, scores, cls = msg.tracks.arrays()
    tracks = BoxTracks(column(msg.track_ids, U4, msg.tracks.n, 1, "track_ids").ravel().astype(np.int64), xyxy,
                       scores, cls, np.full(msg.tracks.n, -1))
    if msg.view == "ego":
        return RoifFrame(msg.t_ns * 1e-9, obu, None, None, tracks)
    f, m = msg.fused.n, msg.obu.n
    fxyxy, fscores, fcls = msg.fused.arrays()
    fused = FusedBoxes(fxyxy, fscores, fcls, column(msg.fused_sources, U1, f, 1, "").ravel().astype(np.int64),
                       column(msg.fused_rsu_index, I2, f, 1, "").ravel().astype(np.int64),
                       column(msg.fused_obu_index, I2, f, 1, "").ravel().astype(np.int64))
    mapping = BoxMapping(column(msg.obu_transform, F4, m, 9, "").astype(float).reshape(m, 3, 3),
                         column(msg.obu_mapping, U1, m, 1, "").ravel().astype(np.int64),
                         column(msg.obu_inlier_error_px, F4, m, 1, "").ravel().astype(float), np.full(m, -1))
    empty = np.zeros((0, 2))
    fit = HomographyFit(None, msg.status, msg.keypoints_obu, msg.keypoints_rsu, msg.matches, msg.inliers,
                        msg.frame_inlier_error_px, empty, empty, np.zeros(0, bool))
    result = RoifResult(fused, column(msg.obu_mapped, F4, m, 4, "").astype(float), mapping, fit)
    return RoifFrame(msg.t_ns * 1e-9, obu, view(msg.rsu, wh), result, tracks)


def _percentiles(values: list) -> dict:
    if not values:
        return {"p50": None, "p99": None, "max": None}
    v = np.asarray(values, float)
    return {"p50": round(float(np.percentile(v, 50)), 1), "p99": round(float(np.percentile(v, 99)), 1),
            "max": round(float(v.max()), 1)}


def summary(report: dict) -> str:
    """Human lines of a live ROIF report."""
    from v2i.offline.image_fusion import summary as offline_summary

    live = report["image_fusion_live"]
    return "\n".join([offline_summary(report),
                      f"  live: {live['frames_published']}/{live['frames_expected']} frames published, "
                      f"{live['frames_paired']} paired with an RSU frame, {live['frames_unpaired']} without; "
                      f"output latency p50 {live['output_latency_ms']['p50']} ms, p99 {live['output_latency_ms']['p99']} "
                      f"ms; deadline misses {live['output_deadline_misses']}; refused {live['rejected']}"])
