"""ROIF split at the wire: RsuImageFeatures round trip and every refusal; the split pipeline equals the
image-level one (and the pre-split computation); the OBU's pairing, refusals and degenerate inputs."""

import cv2
import msgpack
import numpy as np
import pytest

from v2i.fusion.roif import (
    RoifConfig,
    fit_homography,
    match_descriptors,
    roif_fuse,
    roif_fuse_images,
)
from v2i.fusion.roif_features import (
    ViewFeatures,
    box_mask,
    keypoint_box_index,
    view_features,
)
from v2i.fusion.roif_pipeline import VIEW_EGO, VIEW_RSU, RoifFramePipeline
from obu_service.image_fusion import ImageFusionConfig, ImageFusionPipeline
from schemas.codec import (
    CodecError,
    InvalidMessage,
    MalformedMessage,
    WrongMessageType,
    decode,
    encode,
)
from schemas.image_messages import F4, U2, ImageFusedBoxes, RsuImageFeatures
from schemas.messages import ObjectList, TimeReply

from roif_images import H_TRUE, OBU_BOXES, H, W, textured

T0 = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def views():
    obu = textured(0)
    rsu = cv2.warpPerspective(obu, H_TRUE, (W, H))
    rsu_boxes = np.array([cv2.boundingRect(cv2.perspectiveTransform(
        b[[[0, 1], [2, 1], [2, 3], [0, 3]]].reshape(-1, 1, 2), H_TRUE).astype(np.float32)) for b in OBU_BOXES], float)
    rsu_boxes[:, 2:] += rsu_boxes[:, :2]
    return obu, (OBU_BOXES, np.array([0.9, 0.6, 0.7]), np.array([1, 2, 5])), rsu, \
        (np.clip(rsu_boxes, 0, [W, H, W, H]), np.array([0.8, 0.7, 0.5]), np.array([1, 2, 5]))


def _message(n_boxes=2, n_kp=50, seed=0, **fields) -> RsuImageFeatures:
    rng = np.random.default_rng(seed)
    boxes = np.array([[10, 10, 200, 150], [300, 100, 500, 300]], float)[:n_boxes]
    kp = rng.uniform(20, 140, (n_kp, 2))
    view = ViewFeatures.of(boxes, np.full(n_boxes, 0.5), np.arange(n_boxes), kp,
                           rng.integers(0, 256, (n_kp, 32)), (W, H))
    msg = RsuImageFeatures.from_view("rsu-1", 7, T0, view)
    return msg.model_copy(update=fields) if fields else msg


def _tampered(mutate) -> bytes:
    env = msgpack.unpackb(encode(_message()), raw=False)
    mutate(env["d"])
    return msgpack.packb(env, use_bin_type=True)


def test_round_trip_is_exact_and_columns_are_bytes():
    msg = _message()
    data = encode(msg)
    assert decode(data, RsuImageFeatures) == msg
    body = msgpack.unpackb(data, raw=False)["d"]
    assert isinstance(body["keypoints"], bytes) and len(body["descriptors"]) == 32 * 50
    view = ViewFeatures.of_message(decode(data, RsuImageFeatures))
    np.testing.assert_array_equal(view.keypoints, np.frombuffer(msg.keypoints, F4).reshape(-1, 2))
    assert view.descriptors.dtype == np.uint8 and view.descriptors.shape == (50, 32)
    assert (view.box_index == 0).all()


def _f32(values) -> bytes:
    return np.asarray(values, F4).tobytes()


@pytest.mark.parametrize("mutate, error, words", [
    (lambda d: d.update(n_keypoints=4097), InvalidMessage, "n_keypoints"),
    (lambda d: d["boxes"].update(n=257), InvalidMessage, "boxes.n"),
    (lambda d: d.update(keypoints=_f32(np.r_[[np.nan, 1.0], np.ones(98)])), InvalidMessage, "keypoint 0"),
    (lambda d: d.update(keypoints=_f32(np.r_[[W + 1.0, 1.0], np.ones(98)])), InvalidMessage, "inside the image"),
    (lambda d: d["boxes"].update(xyxy=_f32([10, 10, W + 5, 150, 300, 100, 500, 300])), InvalidMessage, "not inside"),
    (lambda d: d["boxes"].update(xyxy=_f32([10, 10, 10, 150, 300, 100, 500, 300])), InvalidMessage, "empty box"),
    (lambda d: d["boxes"].update(score=_f32([np.inf, 0.5])), InvalidMessage, "score"),
    (lambda d: d.update(descriptors=d["descriptors"][:-1]), InvalidMessage, "descriptors"),
    (lambda d: d.update(keypoint_box=np.full(50, 2, U2).tobytes()), InvalidMessage, "names box 2"),
    (lambda d: d.update(evil=1), InvalidMessage, "evil"),
    (lambda d: d["boxes"].update(evil=1), InvalidMessage, "evil"),
    (lambda d: d.update(keypoints="not bytes"), InvalidMessage, "keypoints"),
])
def test_every_bad_frame_is_refused_with_its_reason(mutate, error, words):
    with pytest.raises(error) as info:
        decode(_tampered(mutate), RsuImageFeatures)
    assert words in str(info.value)


def test_wrong_type_and_truncation_are_codec_errors():
    with pytest.raises(WrongMessageType):
        decode(encode(_message()), ObjectList)
    with pytest.raises(MalformedMessage):
        decode(encode(_message())[:-7], RsuImageFeatures)


def test_keypoint_box_index_follows_the_orb_mask():
    boxes = np.array([[10.2, 10.2, 20.7, 20.7], [15, 15, 40, 40]])
    kp = np.array([[10.0, 10.0], [20.9, 12.0], [30.0, 30.0], [100.0, 100.0]])
    np.testing.assert_array_equal(keypoint_box_index(kp, boxes), [0, 0, 1, 1])  # rounded outward; else nearest
    assert box_mask((50, 50), boxes)[10, 10] == 255


def test_split_pipeline_equals_the_image_level_one_and_survives_the_wire(views):
    img_o, det_o, img_r, det_r = views
    cfg = RoifConfig()
    old = roif_fuse_images(img_o, det_o, img_r, det_r, cfg)
    obu, rsu = view_features(img_o, det_o, cfg), view_features(img_r, det_r, cfg)
    wire = ViewFeatures.of_message(decode(encode(RsuImageFeatures.from_view("rsu-1", 1, T0, rsu)), RsuImageFeatures))
    assert old.fit.status == "ok" and old.mapped
    for new in (roif_fuse(obu, rsu, cfg), roif_fuse(obu, wire, cfg)):
        np.testing.assert_allclose(new.fused.xyxy, old.fused.xyxy, atol=1e-4)  # boxes travel as float32
        np.testing.assert_array_equal(new.fused.sources, old.fused.sources)
        np.testing.assert_array_equal(new.mapping.how, old.mapping.how)
        np.testing.assert_allclose(new.fit.H, old.fit.H)
        assert new.fit.inliers == old.fit.inliers


def test_features_match_the_pre_split_computation(views):
    """The homography from ORB + BF matching + RANSAC computed here directly, as roif.py did on images."""
    img_o, det_o, img_r, det_r = views
    cfg = RoifConfig()
    orb = cv2.ORB_create(nfeatures=cfg.orb_features, nlevels=cfg.orb_levels, edgeThreshold=cfg.orb_patch_px,
                         patchSize=cfg.orb_patch_px, fastThreshold=cfg.orb_fast_threshold)
    grey = [cv2.cvtColor(i, cv2.COLOR_BGR2GRAY) for i in (img_o, img_r)]
    (ko, do), (kr, dr) = (orb.detectAndCompute(g, box_mask(g.shape, d[0])) for g, d in zip(grey, (det_o, det_r)))
    po, pr = np.array([k.pt for k in ko]), np.array([k.pt for k in kr])
    pairs = match_descriptors(do, dr, cfg)
    H_old, _ = cv2.findHomography(po[pairs[:, 0]], pr[pairs[:, 1]], cv2.RANSAC, cfg.ransac_reproj_px)
    fit = fit_homography(view_features(img_o, det_o, cfg), view_features(img_r, det_r, cfg), cfg)
    np.testing.assert_allclose(fit.H, H_old)


def test_frame_pipeline_without_a_partner_goes_out_in_the_ego_view(views):
    img_o, det_o, img_r, det_r = views
    pipe = RoifFramePipeline()
    obu, rsu = view_features(img_o, det_o, pipe.roif), view_features(img_r, det_r, pipe.roif)
    assert pipe.step(obu, rsu, 0.0).view == VIEW_RSU and pipe.step(obu, rsu, 0.1).view == VIEW_RSU
    lone = pipe.step(obu, None, 0.2)
    assert lone.view == VIEW_EGO and pipe.unpaired == 1
    np.testing.assert_array_equal(lone.fused.xyxy, obu.boxes)
    assert len(lone.tracks.ids) >= 1, "confirmed tracks coast through a frame without an RSU view"


def _synced(pipe: ImageFusionPipeline, rsu_id="rsu-1", offset_ns=250_000_000) -> None:
    for k in range(12):
        t1 = T0 - 5_000_000_000 + k * 100_000_000
        req = pipe.make_time_request(t1)
        reply = TimeReply(rsu_id=rsu_id, seq=req.seq, t1_ns=t1, t2_ns=t1 + 5_000_000 + offset_ns,
                          t3_ns=t1 + 5_100_000 + offset_ns)
        pipe.on_time_reply(reply, t1 + 10_100_000)
    pipe.on_time_reply(reply, T0)  # ripen the held replies


def test_obu_pairs_refuses_by_reason_and_publishes_every_frame(views):
    img_o, det_o, img_r, det_r = views
    pipe = ImageFusionPipeline(ImageFusionConfig(known_rsus=("rsu-1",)))
    obu, rsu = view_features(img_o, det_o, pipe.roif.roif), view_features(img_r, det_r, pipe.roif.roif)
    msg = lambda t_rsu, rsu_id="rsu-1", seq=1: RsuImageFeatures.from_view(rsu_id, seq, t_rsu, rsu)
    assert not pipe.on_features(msg(T0), T0) and pipe.rejected["features_unsynced"] == 1
    _synced(pipe)
    offset = 250_000_000
    assert not pipe.on_features(msg(T0, "other"), T0)
    assert not pipe.on_features(msg(T0 + offset + 900_000_000, seq=2), T0)
    assert not pipe.on_features(msg(T0 + offset - 5_000_000_000, seq=3), T0)
    assert pipe.on_features(msg(T0 + offset, seq=4), T0 + 100_000_000)
    assert not pipe.on_features(msg(T0 + offset, seq=4), T0 + 100_000_000)
    assert {k: pipe.rejected[k] for k in ("features_unknown_rsu", "features_future", "features_stale",
                                          "features_duplicate")} == dict.fromkeys(
        ("features_unknown_rsu", "features_future", "features_stale", "features_duplicate"), 1)
    pipe.on_frame(obu, T0 + 10_000_000)  # 10 ms after the RSU frame (OBU clock): pairs
    assert pipe.ready(T0 + 20_000_000)
    out = decode(encode(pipe.fuse_next(T0 + 150_000_000)), ImageFusedBoxes)
    assert out.view == "rsu" and out.rsu_seq == 4 and out.fused.n >= 3 and out.status == "ok"
    pipe.on_frame(obu, T0 + 200_000_000)  # 200 ms away from any RSU frame: waits, then goes alone
    assert not pipe.ready(T0 + 300_000_000) and pipe.ready(T0 + 500_000_000)
    out = pipe.fuse_next(T0 + 700_000_000)
    assert out.view == "ego" and out.rsu_id is None and pipe.unpaired == 1 and pipe.deadline_misses == 1
    # its partner arrives after it went out alone: too late, refused as such, not buffered
    assert not pipe.on_features(msg(T0 + offset + 190_000_000, seq=5), T0 + 750_000_000)
    assert pipe.rejected["features_late"] == 1 and pipe.accepted == 1
    assert pipe.on_features(msg(T0 + offset + 300_000_000, seq=6), T0 + 750_000_000)  # the next frame's: kept


@pytest.mark.parametrize("n_boxes, n_kp, how", [(2, 0, "in"), (2, 300, "nowhere"), (0, 0, "in"), (2, 4096, "in")])
def test_valid_degenerate_frames_fuse_without_error(views, n_boxes, n_kp, how):
    img_o, det_o, _, _ = views
    rng = np.random.default_rng(1)
    boxes = np.array([[10, 10, 60, 60], [10, 10, 60, 60]], float)[:n_boxes]  # duplicates
    kp = rng.uniform(0, [W, H], (n_kp, 2)) if how == "nowhere" else rng.uniform(10, 60, (n_kp, 2))
    index = np.zeros(n_kp, np.int64)
    rsu = ViewFeatures.of(boxes, np.full(n_boxes, 0.5), np.ones(n_boxes), kp, rng.integers(0, 256, (n_kp, 32)),
                          (W, H), index)
    wire = ViewFeatures.of_message(decode(encode(RsuImageFeatures.from_view("rsu-1", 1, T0, rsu)), RsuImageFeatures))
    pipe = RoifFramePipeline()
    frame = pipe.step(view_features(img_o, det_o, pipe.roif), wire, 0.0)
    assert frame.view == VIEW_RSU and len(frame.fused.xyxy) >= n_boxes


def test_codec_errors_are_codec_errors():
    assert issubclass(InvalidMessage, CodecError)
