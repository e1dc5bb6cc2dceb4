"""Offline driver of image-level fusion (``v2i eval --fusion roif``; Maqsud's ROIF thesis Ch. 5-6).

At the ego camera's rate (``scenario.ego_camera.rate_hz``), frame k at t_k = k / rate:
render the RSU view (``v2i.sim.camera.rsu_camera``, swaying as the live RSU's) and the ego view
(``v2i.sim.camera.vehicle_camera`` at the ego's true pose, the ego itself hidden) with
``v2i.sim.render.SceneRenderer``; detect boxes in both (the RSU at the live RSU's score threshold,
ORB features up to its per-frame cap: ``RSU_DEFAULTS``); fuse them with ROIF (``v2i.fusion.roif``:
ORB + RANSAC homography, OBU boxes mapped into the RSU view, eq. 5.6-5.11); track the fused
boxes (``v2i.fusion.box_tracker``); score against the RSU view's ground-truth labels.

Detectors: ``"onnx"`` (``v2i.perception.detector.OnnxDetector``, the shipped model or
``model_path``; the RSU's at ``v2i rsu``'s score threshold, the OBU's at the detector's
default) or ``"labels"``, a stand-in that reads the renderer's ``BoxLabels``: each label with
visible fraction v >= 0.3 is detected with probability p_detect min(1, v / 0.6), its corners
jittered by N(0, (jitter * size)^2), its score U(0.5, 1). The report names the detector used.

Scoring, per frame, against the RSU view's truth T = labels of actors (ids > 0) with visible
>= ``MIN_VISIBLE`` (0.3). Boxes match truths one-to-one (Hungarian on 1 - IoU) at IoU >= 0.5,
class-agnostic. Labels not in T (the ego, id 0, which the RSU sees; actors barely visible)
are "ignore" boxes: an unmatched box with IoU >= 0.5 against one is neither right nor wrong.

    detection_accuracy = matched truths / truths            (fused boxes; Maqsud's ROIF thesis: 93 %)
    rsu_only_detection_accuracy                             (the RSU's boxes alone; 91 %)
    vehicle_only_detection_accuracy                         (the OBU's boxes as ROIF maps them
        into the RSU view, alone, against the same T: a box ROIF could not map counts as a
        miss; Maqsud's ROIF thesis: 37 %)
    vehicle_only_scene_accuracy                             (objects of T the OBU detects in its
        own image, matched to the ego-view truth of the same object: the vehicle's share of the
        scene without the cost of mapping)
    vehicle_own_view_accuracy                               (the OBU's boxes against the ego
        view's own truth: the detector, not the scene)
    tracked_detection_accuracy                              (confirmed tracks, coasting included)
    precision = matched boxes / (boxes - ignored boxes)     (fused; also RSU-only, vehicle-only)
    mean_iou = mean IoU of matched (fused box, truth) pairs (Maqsud's ROIF thesis: 0.72)
    reprojection_error_px: mean over frames of the mean corner error 1/2 (|tl' - tl| + |br' - br|)
        of the OBU boxes that match (IoU >= 0.5) the ego-view truth of an object of T, as mapped
        into the RSU view, against that object's RSU-view truth box (how the ROIF thesis validated
        its 4.3 px); ``_rel``: the same over the truth box's diagonal; ``_gt_box_px``: the
        ego-view truth box through the same transform (the mapping alone, no detector error);
        ``ransac_inlier_error_px``: mean over frames of the RANSAC inliers' mean error of the
        transforms used, ``frame_homography_inlier_error_px`` that of the frame homography.
    homography_failures: frames in which the OBU had boxes and none was mapped, by reason
        (``homography_failure_reasons``); ``frame_homography_failures``: frames without a
        frame homography (the thesis' failure: too few features, matches or inliers).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from v2i.fusion.association import assign
from v2i.fusion.box_tracker import BoxTrackerConfig
from v2i.fusion.roif import (
    MAPPED_FRAME,
    MAPPED_NONE,
    MAPPED_OWN,
    OK,
    RoifConfig,
    iou_matrix,
    map_boxes,
)
from v2i.fusion.roif_features import ViewFeatures, view_features
from v2i.fusion.roif_pipeline import RoifFrame, RoifFramePipeline
from rsu_service.config import RsuConfig
from v2i.sim.camera import rsu_camera, rsu_sway, vehicle_camera
from v2i.sim.scenario import load_scenario
from v2i.sim.seeding import stream
from v2i.sim.world import World

MIN_VISIBLE = 0.3  # least visible fraction of a truth that counts
MATCH_IOU = 0.5  # IoU a box needs to match a truth
DEFAULT_SCENARIO = "roif-intersection"
DETECTORS = ("onnx", "labels")
# the live RSU's score threshold and per-frame ORB cap (v2i rsu --score-threshold, --image-features-max)
RSU_DEFAULTS = {name: RsuConfig.model_fields[name].default for name in ("score_threshold", "image_features_max")}
NO_OBJECT_TRANSFORM = "no_object_transform"  # a frame homography, but no OBU box had its own transform


@dataclass(frozen=True)
class LabelDetectorConfig:
    p_detect: float = 0.9  # detection probability of a label with visible fraction >= 0.6
    jitter: float = 0.04  # corner noise std as a fraction of the box's width / height
    min_visible: float = MIN_VISIBLE


class LabelDetector:
    """The stand-in detector: boxes from the renderer's labels with seeded misses and noise."""

    name = "labels"

    def __init__(self, rng: np.random.Generator, config: LabelDetectorConfig = LabelDetectorConfig()):
        self.rng, self.config = rng, config

    def boxes(self, frame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(xyxy (N, 4) px, scores (N,), cls (N,)) of a ``RenderedFrame``."""
        c, lab = self.config, frame.labels
        p = c.p_detect * np.minimum(1.0, np.asarray(lab.visible, float) / 0.6)
        hit = (np.asarray(lab.visible) >= c.min_visible) & (self.rng.random(len(p)) < p)
        xyxy = np.asarray(lab.xyxy, float)[hit]
        size = np.tile(xyxy[:, 2:] - xyxy[:, :2], 2)
        xyxy = xyxy + self.rng.normal(0.0, c.jitter, xyxy.shape) * size
        xyxy = np.column_stack([np.minimum(xyxy[:, :2], xyxy[:, 2:]), np.maximum(xyxy[:, :2], xyxy[:, 2:])])
        h, w = frame.image.shape[:2]
        xyxy = np.clip(xyxy, 0.0, [w, h, w, h])
        return xyxy, self.rng.uniform(0.5, 1.0, len(xyxy)), np.asarray(lab.cls, np.int64)[hit]


class OnnxBoxes:
    """``v2i.perception.detector.OnnxDetector`` on the frame's image."""

    name = "onnx"

    def __init__(self, model_path=None, score_threshold: float | None = None):
        from v2i.perception.detector import OnnxDetector

        kw = {} if score_threshold is None else {"score_threshold": score_threshold}
        self.detector = OnnxDetector(model_path, **kw)

    def boxes(self, frame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        d = self.detector.detect(frame.image)
        return np.asarray(d.xyxy, float).reshape(-1, 4), np.asarray(d.scores, float), np.asarray(d.cls, np.int64)


@dataclass
class BoxTally:
    """Detection counts of one kind of box over frames."""

    truths: int = 0
    matched: int = 0
    boxes: int = 0
    ignored: int = 0
    iou_sum: float = 0.0

    def add(self, boxes: np.ndarray, truth: np.ndarray, ignore: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One frame: boxes (B, 4), truths (T, 4), ignore boxes (G, 4) px; the matches
        (truth index (M,), box index (M,))."""
        boxes = np.asarray(boxes, float).reshape(-1, 4)
        boxes = boxes[np.isfinite(boxes).all(axis=1)]
        iou = iou_matrix(truth, boxes)
        m = assign(1.0 - iou, gate=1.0 - MATCH_IOU).matches
        lone = np.setdiff1d(np.arange(len(boxes)), m[:, 1])
        self.truths += len(truth)
        self.matched += len(m)
        self.boxes += len(boxes)
        if len(lone) and len(ignore):
            self.ignored += int((iou_matrix(boxes[lone], ignore).max(axis=1) >= MATCH_IOU).sum())
        self.iou_sum += float(iou[m[:, 0], m[:, 1]].sum())
        return m[:, 0], m[:, 1]

    def accuracy(self) -> float | None:
        return round(self.matched / self.truths, 4) if self.truths else None

    def precision(self) -> float | None:
        counted = self.boxes - self.ignored
        return round(self.matched / counted, 4) if counted else None

    def mean_iou(self) -> float | None:
        return round(self.iou_sum / self.matched, 4) if self.matched else None


@dataclass
class FusionTally:
    """Everything the ``image_fusion`` section reports, accumulated frame by frame."""

    fused: BoxTally = field(default_factory=BoxTally)
    rsu: BoxTally = field(default_factory=BoxTally)
    vehicle: BoxTally = field(default_factory=BoxTally)
    vehicle_own: BoxTally = field(default_factory=BoxTally)
    vehicle_scene_found: int = 0  # objects of T the OBU detected in its own image
    tracked: BoxTally = field(default_factory=BoxTally)
    frames: int = 0
    failures: dict = field(default_factory=dict)  # frames with OBU boxes and none mapped, by reason
    frame_failures: dict = field(default_factory=dict)  # frames without a frame homography, by reason
    corner_err_px: list = field(default_factory=list)  # per frame: mean corner error of mapped OBU boxes
    corner_err_rel: list = field(default_factory=list)  # the same over the truth box diagonal
    gt_corner_err_px: list = field(default_factory=list)  # the same with the ego-view truth boxes mapped
    inlier_err_px: list = field(default_factory=list)  # per frame: inlier error of the transforms used
    frame_inlier_err_px: list = field(default_factory=list)  # per frame: the frame homography's inlier error
    inliers: list = field(default_factory=list)
    fused_pairs: int = 0  # boxes fused from both views
    mapped_own: int = 0  # OBU boxes mapped through their own homography
    mapped_frame: int = 0  # OBU boxes mapped through the frame's homography
    track_ids: dict = field(default_factory=dict)  # truth id -> track ids that matched it

    def section(self) -> dict:
        def mean(v):
            return round(float(np.mean(v)), 3) if len(v) else None

        return {
            "detection_accuracy": self.fused.accuracy(),
            "vehicle_only_detection_accuracy": self.vehicle.accuracy(),
            "rsu_only_detection_accuracy": self.rsu.accuracy(),
            "vehicle_only_scene_accuracy": round(self.vehicle_scene_found / self.fused.truths, 4) if self.fused.truths else None,
            "vehicle_own_view_accuracy": self.vehicle_own.accuracy(),
            "tracked_detection_accuracy": self.tracked.accuracy(),
            "precision": self.fused.precision(),
            "rsu_only_precision": self.rsu.precision(),
            "vehicle_only_precision": self.vehicle.precision(),
            "mean_iou": self.fused.mean_iou(),
            "rsu_only_mean_iou": self.rsu.mean_iou(),
            "reprojection_error_px": mean(self.corner_err_px),
            "reprojection_error_rel": mean(self.corner_err_rel),
            "reprojection_error_gt_box_px": mean(self.gt_corner_err_px),
            "ransac_inlier_error_px": mean(self.inlier_err_px),
            "frame_homography_inlier_error_px": mean(self.frame_inlier_err_px),
            "frame_homography_mean_inliers": mean(self.inliers),
            "frames": self.frames,
            "truths": self.fused.truths,
            "fused_pairs": self.fused_pairs,
            "obu_boxes_mapped_own": self.mapped_own,
            "obu_boxes_mapped_frame": self.mapped_frame,
            "homography_failures": sum(self.failures.values()),
            "homography_failure_reasons": dict(sorted(self.failures.items())),
            "frame_homography_failures": sum(self.frame_failures.values()),
            "frame_homography_failure_reasons": dict(sorted(self.frame_failures.items())),
            "track_id_switches": sum(max(len(ids) - 1, 0) for ids in self.track_ids.values()),
        }


def _truth(labels, min_visible: float = MIN_VISIBLE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Truth boxes (T, 4), their actor ids (T,), ignore boxes (G, 4) of a frame's labels."""
    ids, xyxy = np.asarray(labels.ids, np.int64), np.asarray(labels.xyxy, float).reshape(-1, 4)
    real = (ids > 0) & (np.asarray(labels.visible, float) >= min_visible)
    return xyxy[real], ids[real], xyxy[~real]


def corner_error_px(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) mean of the top-left and bottom-right corner distances of boxes a, b (N, 4) px."""
    a, b = np.asarray(a, float).reshape(-1, 4), np.asarray(b, float).reshape(-1, 4)
    return 0.5 * (np.hypot(*(a[:, :2] - b[:, :2]).T) + np.hypot(*(a[:, 2:] - b[:, 2:]).T))


def _detectors(detector: str, model_path, seed: int) -> tuple:
    """(RSU view detector, ego view detector); the stand-in draws from its own seeded streams."""
    if detector == "onnx":  # the RSU at v2i rsu's --score-threshold, the OBU at the detector's default
        return OnnxBoxes(model_path, RSU_DEFAULTS["score_threshold"]), OnnxBoxes(model_path)
    if detector == "labels":
        rngs = [np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0x501F, k))) for k in range(2)]
        return LabelDetector(rngs[0]), LabelDetector(rngs[1])
    raise ValueError(f"detector must be one of {DETECTORS}, got {detector!r}")


def _vehicle_view(tally: FusionTally, result, obu_boxes: np.ndarray, ego_labels, rsu_truth: np.ndarray,
                  rsu_ids: np.ndarray, rsu_wh: tuple[int, int]) -> None:
    """The OBU's boxes (M, 4) against the ego-view truth of the objects of T: which it found
    (scene accuracy) and, for those ROIF mapped, the corner errors of the mapped box and of the
    ego-view truth box through the same transform against the RSU-view truth."""
    ids, xyxy, m = _vehicle_scene(tally, obu_boxes, ego_labels, rsu_ids)
    m = m[result.mapping.how[m[:, 1]] != MAPPED_NONE]
    if not len(m):
        return
    rsu_box = {int(i): b for i, b in zip(rsu_ids, rsu_truth)}
    target = np.array([rsu_box[int(i)] for i in ids[m[:, 0]]])
    diagonal = np.hypot(target[:, 2] - target[:, 0], target[:, 3] - target[:, 1])
    mapped = result.mapped_obu_xyxy[m[:, 1]]
    gt_mapped = np.vstack([map_boxes(result.mapping.transform[j], xyxy[i:i + 1], rsu_wh) for i, j in m])
    ok = np.isfinite(mapped).all(axis=1)
    if ok.any():
        err = corner_error_px(mapped[ok], target[ok])
        tally.corner_err_px.append(float(err.mean()))
        tally.corner_err_rel.append(float((err / diagonal[ok]).mean()))
    ok = np.isfinite(gt_mapped).all(axis=1)
    if ok.any():
        tally.gt_corner_err_px.append(float(corner_error_px(gt_mapped[ok], target[ok]).mean()))


def _vehicle_scene(tally: FusionTally, obu_boxes: np.ndarray, ego_labels, rsu_ids: np.ndarray) -> tuple:
    """The objects of T the OBU found in its own image: ego-view truth ids (E,) and boxes (E, 4)
    of the objects of T, and the (truth, OBU box) matches (M, 2) at IoU >= 0.5."""
    ids, xyxy = np.asarray(ego_labels.ids, np.int64), np.asarray(ego_labels.xyxy, float).reshape(-1, 4)
    keep = np.isin(ids, rsu_ids)
    ids, xyxy = ids[keep], xyxy[keep]
    m = assign(1.0 - iou_matrix(xyxy, obu_boxes), gate=1.0 - MATCH_IOU).matches
    tally.vehicle_scene_found += len(m)
    return ids, xyxy, m


def _count_mapping(tally: FusionTally, result, obu_box_count: int) -> None:
    """Frame homography (the thesis' one per frame) and box mapping counts of one frame."""
    fit = result.fit
    if fit.status == OK:
        tally.frame_inlier_err_px.append(fit.reprojection_px)
        tally.inliers.append(fit.inliers)
    else:
        tally.frame_failures[fit.status] = tally.frame_failures.get(fit.status, 0) + 1
    used = result.mapping.inlier_error_px[result.mapping.how != MAPPED_NONE]
    if len(used):
        tally.inlier_err_px.append(float(used.mean()))
    elif obu_box_count:  # the OBU saw something and none of it reached the RSU view
        reason = fit.status if fit.status != OK else NO_OBJECT_TRANSFORM
        tally.failures[reason] = tally.failures.get(reason, 0) + 1


def score_frame(tally: FusionTally, frame: RoifFrame, rsu_labels, ego_labels) -> None:
    """Every tally of one stepped frame against the RSU view's labels and the ego view's labels
    (``BoxLabels``). A frame without an RSU partner (live only) has no boxes in the RSU view:
    its truths count as missed by the fused, RSU-only and mapped lists; its tracks still count."""
    truth, truth_ids, ignore = _truth(rsu_labels)
    empty = np.zeros((0, 4))
    tally.frames += 1
    result, obu_xyxy = frame.result, frame.obu.boxes
    ego_truth, _, ego_ignore = _truth(ego_labels)
    tally.vehicle_own.add(obu_xyxy, ego_truth, ego_ignore)
    if result is not None:
        fused = result.fused
        _count_mapping(tally, result, len(obu_xyxy))
        tally.fused_pairs += int(np.count_nonzero(fused.rsu_index[fused.obu_index >= 0] >= 0))
        tally.mapped_own += int(np.count_nonzero(result.mapping.how == MAPPED_OWN))
        tally.mapped_frame += int(np.count_nonzero(result.mapping.how == MAPPED_FRAME))
    tally.fused.add(empty if result is None else result.fused.xyxy, truth, ignore)
    tally.rsu.add(empty if frame.rsu is None else frame.rsu.boxes, truth, ignore)
    tally.vehicle.add(empty if result is None else result.mapped_obu_xyxy, truth, ignore)
    ti, bi = tally.tracked.add(frame.tracks.xyxy, truth, ignore)
    for i, b in zip(truth_ids[ti], frame.tracks.ids[bi]):
        tally.track_ids.setdefault(int(i), set()).add(int(b))
    if result is not None:
        _vehicle_view(tally, result, obu_xyxy, ego_labels, truth, truth_ids, frame.rsu.image_wh)
    else:
        _vehicle_scene(tally, obu_xyxy, ego_labels, truth_ids)


def run_image_fusion(scenario: str = DEFAULT_SCENARIO, seed: int = 0, duration_s: float | None = None,
                     detector: str = "onnx", model_path: str | None = None, roif: RoifConfig | None = None,
                     tracker: BoxTrackerConfig | None = None, rsu_max_features: int | None = None,
                     wire: bool = False) -> dict:
    """ROIF over a scenario with an ``ego_camera``: the run's identification and its ``image_fusion``
    section. Deterministic for a seed. ``duration_s`` None: the scenario's; ``detector``: "onnx"
    (``model_path`` None: the shipped model) or "labels" (the stand-in). ``rsu_max_features``: the
    RSU's per-frame ORB cap (default the live RSU's, ``RSU_DEFAULTS``); ``wire``: the RSU's
    features reach the fusion through an encoded ``RsuImageFeatures`` (as on the live link; the
    report's ``rsu_features`` gives the message sizes)."""
    from v2i.sim.render import SceneRenderer

    sc = load_scenario(scenario)
    if sc.ego_camera is None:
        raise ValueError(f"scenario {sc.name!r} has no ego_camera: --fusion roif needs one (see roif-intersection)")
    world = World(sc)
    renderer = SceneRenderer(world, seed=seed)
    det_rsu, det_obu = _detectors(detector, model_path, seed)
    cam_rsu, sway = rsu_camera(sc.rsu), rsu_sway(sc.rsu, stream(seed, "rsu_sway"))  # as the live RSU's camera
    rsu_max_features = RSU_DEFAULTS["image_features_max"] if rsu_max_features is None else rsu_max_features
    noise_rsu, noise_ego = stream(seed, "rsu_render"), stream(seed, "ego_render")
    rate_hz = sc.ego_camera.rate_hz
    duration = sc.duration_s if duration_s is None else min(float(duration_s), sc.duration_s)
    pipeline = RoifFramePipeline(roif, tracker)
    tally, wire_bytes = FusionTally(), []
    for k in range(int(np.ceil(duration * rate_hz - 1e-9))):
        t_s = k / rate_hz
        rsu_frame = renderer.render(sway.move(cam_rsu, t_s), t_s, noise_rsu)
        ego_frame = renderer.render(vehicle_camera(sc.ego_camera, world.ego_at(t_s)), t_s, noise_ego, hide_ego=True)
        rsu = view_features(rsu_frame.image, det_rsu.boxes(rsu_frame), pipeline.roif, rsu_max_features)
        if wire:
            rsu = _through_wire(rsu, k, wire_bytes)
        obu = view_features(ego_frame.image, det_obu.boxes(ego_frame), pipeline.roif)
        score_frame(tally, pipeline.step(obu, rsu, t_s), rsu_frame.labels, ego_frame.labels)
    report = {"driver": "eval", "scenario": sc.name, "fusion": "roif", "seed": seed, "duration_s": duration,
              "detector": det_rsu.name, "camera_rate_hz": rate_hz, "image_fusion": tally.section()}
    report["rsu_features"] = {"max_per_frame": rsu_max_features, "wire": wire,
                              **({"message_bytes": _percentiles(wire_bytes)} if wire else {})}
    return report


def _through_wire(rsu: ViewFeatures, seq: int, sizes: list) -> ViewFeatures:
    """The RSU's features as the OBU decodes them from an ``RsuImageFeatures`` message (its size in ``sizes``)."""
    from schemas.codec import decode, encode
    from schemas.image_messages import RsuImageFeatures

    data = encode(RsuImageFeatures.from_view("rsu", seq, 10**18, rsu))
    sizes.append(len(data))
    return ViewFeatures.of_message(decode(data, RsuImageFeatures))


def _percentiles(values: list) -> dict:
    """{p50, p99, max} of a list of numbers (None when empty)."""
    if not values:
        return {"p50": None, "p99": None, "max": None}
    v = np.asarray(values, float)
    return {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)), "max": float(v.max())}


def summary(report: dict) -> str:
    """Human lines of a ``run_image_fusion`` report, beside the ROIF thesis's figures."""
    f = report["image_fusion"]

    def pct(v) -> str:
        return "n/a" if v is None else f"{v:.0%}"

    return "\n".join([
        f"{report['scenario']} | fusion roif | detector {report['detector']} | seed {report['seed']} | "
        f"{f['frames']} frames at {report['camera_rate_hz']:g} Hz",
        f"  detection accuracy: fused {pct(f['detection_accuracy'])}, vehicle-only "
        f"{pct(f['vehicle_only_detection_accuracy'])}, RSU-only {pct(f['rsu_only_detection_accuracy'])} "
        "(ROIF thesis: 93 %, 37 %, 91 %)",
        f"  fused boxes: mean IoU {f['mean_iou']} (0.72), precision {pct(f['precision'])}; re-projection error "
        f"{f['reprojection_error_px']} px (4.3 px); homography failures {f['homography_failures']}",
    ])
