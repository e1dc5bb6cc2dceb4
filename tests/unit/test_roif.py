"""ROIF (seed 004): homography from ORB matches inside boxes, IoU (eq. 5.1-5.5), confidence-weighted
box fusion (eq. 5.6-5.11), the IoU gate, failures counted, the box tracker against filterpy."""

import cv2
import numpy as np
import pytest
import shapely
from filterpy.kalman import KalmanFilter

from v2i.fusion import box_tracker
from v2i.fusion.box_tracker import BoxTracker, BoxTrackerConfig
from v2i.fusion.roif import (
    FEW_FEATURES,
    MAPPED_FRAME,
    MAPPED_OWN,
    OK,
    SOURCE_OBU,
    SOURCE_RSU,
    RoifConfig,
    fit_homography_images,
    fuse_boxes,
    fuse_pair,
    iou_matrix,
    map_boxes,
    map_points,
    roif_fuse_images,
)

from roif_images import H_TRUE, OBU_BOXES, H, W, textured


@pytest.fixture(scope="module")
def views():
    obu = textured(0)
    return obu, cv2.warpPerspective(obu, H_TRUE, (W, H))


def test_homography_recovered_from_a_known_warp(views):
    obu, rsu = views
    fit = fit_homography_images(obu, OBU_BOXES, rsu, map_boxes(H_TRUE, OBU_BOXES, (W, H)))
    assert fit.status == OK and fit.inliers >= 100
    # re-projection error of the recovered H against the true one over the boxes: < 1 px
    u, v = np.meshgrid(np.linspace(50, 600, 12), np.linspace(50, 360, 8))
    grid = np.column_stack([u.ravel(), v.ravel()])
    assert np.linalg.norm(map_points(fit.H, grid) - map_points(H_TRUE, grid), axis=1).mean() < 1.0
    corners = OBU_BOXES.reshape(-1, 2)
    np.testing.assert_allclose(map_points(fit.H, corners), map_points(H_TRUE, corners), atol=1.0)
    assert fit.reprojection_px < 1.5  # RANSAC inliers: ORB keypoints on coarse pyramid levels sit ~1 px off
    # the mapped boxes land on the truth within a pixel, and fuse one-to-one with the RSU's boxes
    truth = map_boxes(H_TRUE, OBU_BOXES, (W, H))
    result = roif_fuse_images(obu, (OBU_BOXES, np.full(3, 0.8), np.ones(3)), rsu, (truth, np.full(3, 0.8), np.ones(3)),
                       RoifConfig(mapping="frame"))
    np.testing.assert_allclose(result.mapped_obu_xyxy, truth, atol=1.0)
    assert np.all(result.mapping.how == MAPPED_FRAME)
    assert np.all(result.fused.sources == SOURCE_RSU | SOURCE_OBU)


def test_each_box_through_its_own_transform_when_the_scene_is_no_plane():
    """Two objects at different depths: the RSU view is the OBU view warped by a different
    homography on each side. One frame homography fits one side; each box's own fits both."""
    obu = textured(1)
    h_left = H_TRUE
    h_right = np.array([[1.15, 0.02, -90.0], [0.01, 1.1, -30.0], [5e-5, 1e-4, 1.0]])
    left, right = np.zeros((H, W), np.uint8), np.zeros((H, W), np.uint8)
    left[:, :W // 2], right[:, W // 2:] = 255, 255
    rsu = np.zeros_like(obu)
    for h, region in ((h_left, left), (h_right, right)):
        warped_mask = cv2.warpPerspective(region, h, (W, H), flags=cv2.INTER_NEAREST) > 0
        rsu[warped_mask] = cv2.warpPerspective(obu, h, (W, H))[warped_mask]
    boxes = np.array([[40, 60, 280, 300], [380, 60, 620, 300]], float)
    truth = np.vstack([map_boxes(h_left, boxes[:1], (W, H)), map_boxes(h_right, boxes[1:], (W, H))])
    dets_rsu = (truth, np.full(2, 0.8), np.ones(2))
    own = roif_fuse_images(obu, (boxes, np.full(2, 0.8), np.ones(2)), rsu, dets_rsu, RoifConfig(object_model="homography"))
    assert own.mapping.how.tolist() == [MAPPED_OWN, MAPPED_OWN] and own.mapping.rsu_box.tolist() == [0, 1]
    np.testing.assert_allclose(own.mapped_obu_xyxy, truth, atol=1.5)
    assert np.all(own.mapping.inlier_error_px < 1.5)
    frame = roif_fuse_images(obu, (boxes, np.full(2, 0.8), np.ones(2)), rsu, dets_rsu, RoifConfig(mapping="frame"))
    worst = np.abs(frame.mapped_obu_xyxy - truth).max(axis=1)
    assert frame.homography is not None and worst.min() < 3.0 and worst.max() > 15.0


def test_keypoints_only_inside_the_boxes(views):
    obu, rsu = views
    fit = fit_homography_images(obu, OBU_BOXES[:1], rsu, map_boxes(H_TRUE, OBU_BOXES[:1], (W, H)))
    x1, y1, x2, y2 = OBU_BOXES[0]
    p = fit.obu_px
    assert len(p) and np.all((p[:, 0] >= x1) & (p[:, 0] <= x2) & (p[:, 1] >= y1) & (p[:, 1] <= y2))


def test_iou_matches_a_hand_computation_and_shapely():
    a, b = np.array([[0, 0, 4, 4]], float), np.array([[2, 2, 6, 6], [4, 0, 8, 4], [1, 1, 3, 3]], float)
    # overlap 2 x 2 = 4, union 16 + 16 - 4 = 28; touching edges: 0; b inside a: 4 / 16
    np.testing.assert_allclose(iou_matrix(a, b), [[4 / 28, 0.0, 0.25]])
    rng = np.random.default_rng(3)
    lo = rng.uniform(0, 100, (40, 2))
    boxes = np.hstack([lo, lo + rng.uniform(1, 60, (40, 2))])
    polys = shapely.box(boxes[:, 0], boxes[:, 1], boxes[:, 2], boxes[:, 3])
    inter = shapely.area(shapely.intersection(polys[:, None], polys[None, :]))
    union = shapely.area(shapely.union(polys[:, None], polys[None, :]))
    np.testing.assert_allclose(iou_matrix(boxes, boxes), inter / union, atol=1e-12)


def test_fusion_weights_follow_eq_5_6_to_5_11():
    red, green = np.array([[10.0, 20.0, 50.0, 60.0]]), np.array([[14.0, 16.0, 54.0, 70.0]])
    fused = fuse_pair(red, [0.9], green, [0.3])[0]
    # x_tl = (10 * 0.9 + 14 * 0.3) / 1.2 = 11, y_tl = (20 * 0.9 + 16 * 0.3) / 1.2 = 19,
    # x_br = (50 * 0.9 + 54 * 0.3) / 1.2 = 51, y_br = (60 * 0.9 + 70 * 0.3) / 1.2 = 62.5
    np.testing.assert_allclose(fused, [11.0, 19.0, 51.0, 62.5])
    assert fused[2] - fused[0] == pytest.approx(40.0) and fused[3] - fused[1] == pytest.approx(43.5)  # 5.10, 5.11
    out = fuse_boxes((red, [0.9], [3]), (green, [0.3], [5]))
    np.testing.assert_allclose(out.xyxy, [fused])
    assert out.scores.tolist() == [0.9] and out.cls.tolist() == [3]  # the more confident box's class
    assert out.rsu_index.tolist() == [0] and out.obu_index.tolist() == [0]


def _pair_with_iou(iou: float) -> tuple[np.ndarray, np.ndarray]:
    """Two 10 x 10 boxes shifted in x so that their IoU is ``iou``: overlap o, o / (200 - o) = iou."""
    overlap = 200.0 * iou / (1.0 + iou) / 10.0
    return np.array([[0.0, 0.0, 10.0, 10.0]]), np.array([[10.0 - overlap, 0.0, 20.0 - overlap, 10.0]])


def test_iou_gate_rejects_below_0_1():
    for iou, fused in ((0.099, False), (0.101, True)):
        red, green = _pair_with_iou(iou)
        assert iou_matrix(red, green)[0, 0] == pytest.approx(iou)
        out = fuse_boxes((red, [0.8], [3]), (green, [0.7], [3]), iou_gate=0.1)
        assert len(out.xyxy) == (1 if fused else 2)
        if not fused:  # both pass through, each from its own source
            assert sorted(out.sources.tolist()) == [SOURCE_RSU, SOURCE_OBU]
            np.testing.assert_allclose(out.xyxy, np.vstack([red, green]))


def test_one_to_one_assignment_prefers_the_larger_overlap():
    red = np.array([[0, 0, 10, 10], [8, 0, 18, 10]], float)
    green = np.array([[7, 0, 17, 10]], float)  # overlaps both RSU boxes, the second far more
    out = fuse_boxes((red, [0.5, 0.5], [3, 3]), (green, [0.5], [3]))
    assert len(out.xyxy) == 2 and out.rsu_index[out.obu_index == 0].tolist() == [1]


def test_too_few_features_gives_no_mapping_and_the_rsu_list():
    flat = np.full((H, W, 3), 128, np.uint8)
    boxes = OBU_BOXES[:2]
    result = roif_fuse_images(flat, (boxes, [0.9, 0.9], [3, 3]), flat, (boxes, [0.8, 0.8], [3, 3]))
    assert result.homography is None and result.fit.status == FEW_FEATURES and not result.mapped
    assert np.isnan(result.mapped_obu_xyxy).all()
    np.testing.assert_allclose(result.fused.xyxy, boxes)
    assert result.fused.sources.tolist() == [SOURCE_RSU, SOURCE_RSU]


def test_a_frame_without_mapping_is_counted_by_reason():
    from v2i.offline.image_fusion import FusionTally, _count_mapping

    flat = np.full((H, W, 3), 128, np.uint8)
    tally = FusionTally()
    result = roif_fuse_images(flat, (OBU_BOXES, np.ones(3), np.ones(3)), flat, (OBU_BOXES, np.ones(3), np.ones(3)))
    _count_mapping(tally, result, obu_box_count=3)
    section = tally.section()
    assert section["homography_failures"] == 1 and section["homography_failure_reasons"] == {FEW_FEATURES: 1}
    assert section["frame_homography_failures"] == 1 and section["ransac_inlier_error_px"] is None


def test_unrelated_views_give_no_mapping(views):
    result = roif_fuse_images(views[0], (OBU_BOXES, np.ones(3), np.ones(3)), textured(7), (OBU_BOXES, np.ones(3), np.ones(3)),
                       RoifConfig(min_inliers=12))
    assert result.homography is None and result.fit.status != OK and result.fit.inliers < 12
    assert not result.mapped and len(result.fused.xyxy) == 3  # the RSU's boxes, nothing mapped


def test_no_boxes_no_crash(views):
    empty = np.zeros((0, 4))
    result = roif_fuse_images(views[0], (empty, [], []), views[1], (empty, [], []))
    assert result.homography is None and len(result.fused.xyxy) == 0


def test_box_kf_matches_filterpy():
    rng = np.random.default_rng(5)
    cfg = BoxTrackerConfig()
    n = 3
    x = np.hstack([rng.uniform(50, 300, (n, 4)), rng.normal(0, 20, (n, 4))])
    p = np.stack([np.diag(rng.uniform(1, 50, 8)) for _ in range(n)])
    refs = []
    for i in range(n):
        kf = KalmanFilter(dim_x=8, dim_z=4)
        kf.x, kf.P, kf.H = x[i].copy()[:, None], p[i].copy(), box_tracker.H_BOX
        kf.R = cfg.measurement_std_px**2 * np.eye(4)
        refs.append(kf)
    for _ in range(200):
        dt = rng.uniform(0.03, 0.3)
        x, p = box_tracker.kf_predict(x, p, dt, cfg.accel_std_pxps2)
        for kf in refs:
            kf.predict(F=box_tracker.transition(dt), Q=box_tracker.process_noise(dt, cfg.accel_std_pxps2))
        idx = np.flatnonzero(rng.random(n) < 0.7)  # some tracks miss
        z = x[idx, :4] + rng.normal(0, 5, (len(idx), 4))
        x[idx], p[idx] = box_tracker.kf_update(x[idx], p[idx], z, refs[0].R)
        for j, i in enumerate(idx):
            refs[i].update(z[j])
        np.testing.assert_allclose(x, np.hstack([kf.x for kf in refs]).T, rtol=0, atol=1e-9)
        np.testing.assert_allclose(p, np.stack([kf.P for kf in refs]), rtol=0, atol=1e-9)


def test_tracker_keeps_ids_through_a_short_miss():
    tracker = BoxTracker(BoxTrackerConfig(confirm_hits=2, max_misses=3))
    dt, v = 0.1, np.array([30.0, 0.0, 30.0, 0.0])  # both boxes move right at 30 px/s

    def boxes(k):
        return np.array([[100, 100, 160, 140], [300, 200, 380, 260]], float) + k * dt * v

    seen = {}
    for k in range(12):
        rows = [0, 1] if k not in (5, 6) else [1]  # box 0 missed for two frames
        out = tracker.step(boxes(k)[rows], np.full(len(rows), 0.9), np.full(len(rows), 3), k * dt)
        for track_id, det in zip(out.ids, out.detection):
            if det >= 0:
                seen.setdefault(rows[det], set()).add(int(track_id))
        if k in (5, 6):  # the missed box coasts at its predicted place
            coast = out.xyxy[out.detection < 0]
            assert len(coast) == 1 and iou_matrix(coast, boxes(k)[:1])[0, 0] > 0.8
    assert seen == {0: {1}, 1: {2}}
    # a longer gap deletes the track; the box comes back under a new id
    for k in range(12, 17):
        tracker.step(boxes(k)[[1]], [0.9], [3], k * dt)
    out = tracker.step(boxes(17), [0.9, 0.9], [3, 3], 17 * dt)
    assert 1 not in out.ids.tolist() and out.ids.tolist() == [2]  # the newcomer is tentative
    out = tracker.step(boxes(18), [0.9, 0.9], [3, 3], 18 * dt)
    assert sorted(out.ids.tolist()) == [2, 3]


def test_driver_fuses_better_than_the_vehicle_alone():
    """A short run of ``v2i eval --fusion roif``'s driver on roif-intersection (label stand-in detector)."""
    from v2i.offline.image_fusion import run_image_fusion

    report = run_image_fusion("roif-intersection", seed=3, duration_s=2.0, detector="labels")
    f = report["image_fusion"]
    assert report["fusion"] == "roif" and report["detector"] == "labels" and f["frames"] == 20
    assert f["detection_accuracy"] > f["vehicle_only_detection_accuracy"] + 0.2
    assert f["detection_accuracy"] >= f["rsu_only_detection_accuracy"] - 0.05
    assert f["precision"] > 0.9 and f["obu_boxes_mapped_own"] > 0 and f["fused_pairs"] > 0
    assert 0.5 < f["mean_iou"] <= 1.0 and 0.0 < f["reprojection_error_px"] < 60.0


def test_driver_is_deterministic_for_a_seed():
    from v2i.offline.image_fusion import run_image_fusion

    runs = [run_image_fusion("roif-intersection", seed=5, duration_s=0.5, detector="labels") for _ in range(2)]
    assert runs[0] == runs[1]


def test_driver_needs_an_ego_camera():
    from v2i.offline.image_fusion import run_image_fusion

    with pytest.raises(ValueError, match="ego_camera"):
        run_image_fusion("red-light-runner", duration_s=0.1, detector="labels")
