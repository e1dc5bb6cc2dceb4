"""ONNX detector: letterbox, both output layouts, NMS, names mapping, errors, the shipped model."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from v2i.perception.detector import (
    SHIPPED_MODEL, DetectorModelError, Letterbox, OnnxDetector, class_table, letterbox, parse_names,
)
from schemas.classes import ObjectClass

IN_W, IN_H = 96, 64  # tiny model input (W, H)


def constant_model(path, output: np.ndarray, names=None, layout=None, dynamic_input=False) -> str:
    """A model with input 'images' [1, 3, H, W] whose output is ``output`` + 0 * mean(images)."""
    dims = [1, 3, "h", "w"] if dynamic_input else [1, 3, IN_H, IN_W]
    images = helper.make_tensor_value_info("images", TensorProto.FLOAT, dims)
    out = helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(output.shape))
    nodes = [
        helper.make_node("Constant", [], ["k"], value=numpy_helper.from_array(output.astype(np.float32))),
        helper.make_node("ReduceMean", ["images"], ["m"], keepdims=0),
        helper.make_node("Constant", [], ["zero"], value=numpy_helper.from_array(np.float32(0.0))),
        helper.make_node("Mul", ["m", "zero"], ["m0"]),
        helper.make_node("Add", ["k", "m0"], ["output0"]),
    ]
    model = helper.make_model(helper.make_graph(nodes, "const", [images], [out]),
                              opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    meta = {"names": names, "layout": layout}
    for key, value in meta.items():
        if value is not None:
            model.metadata_props.add(key=key, value=value)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return str(path)


# Three candidates in letterboxed input px (cx, cy, w, h): two overlapping cars, one person.
CANDIDATES = np.array([[30.0, 20.0, 20.0, 10.0], [31.0, 21.0, 20.0, 10.0], [70.0, 40.0, 6.0, 16.0],
                       [10.0, 50.0, 8.0, 8.0]])
NAMES = "{0: 'person', 1: 'bicycle', 2: 'car', 3: 'traffic light'}"


def v8_output(channels_first=True) -> np.ndarray:
    """(1, 4+nc, A): per-class scores; candidate 3 is a traffic light, plus empty anchors."""
    scores = np.zeros((6, 4))  # 6 anchors x 4 classes
    scores[0, 2], scores[1, 2], scores[2, 0], scores[3, 3] = 0.9, 0.8, 0.6, 0.95
    scores[1, 0] = 0.1  # a weak second class on anchor 1 does not make it a person
    boxes = np.vstack([CANDIDATES, [[50.0, 10.0, 4.0, 4.0], [5.0, 5.0, 2.0, 2.0]]])
    rows = np.hstack([boxes, scores])[None]  # (1, A, 4+nc)
    return rows.transpose(0, 2, 1) if channels_first else rows


def v5_output() -> np.ndarray:
    """(1, A, 5+nc): objectness * class probability is the score."""
    obj = np.array([0.9, 1.0, 0.75, 1.0, 0.01, 0.0])
    probs = np.zeros((6, 4))
    probs[0, 2], probs[1, 2], probs[2, 0], probs[3, 3], probs[4, 2] = 1.0, 0.8, 0.8, 0.95, 1.0
    boxes = np.vstack([CANDIDATES, [[50.0, 10.0, 4.0, 4.0], [5.0, 5.0, 2.0, 2.0]]])
    return np.hstack([boxes, obj[:, None], probs])[None]


def xyxy(cxcywh):
    c = np.asarray(cxcywh, dtype=float)
    return np.column_stack([c[:, :2] - c[:, 2:] / 2, c[:, :2] + c[:, 2:] / 2])


@pytest.mark.parametrize("layout", ["v8", "v8t", "v5"])
def test_both_layouts_decode_nms_threshold_and_names(tmp_path, layout):
    out = {"v8": v8_output(True), "v8t": v8_output(False), "v5": v5_output()}[layout]
    det = OnnxDetector(constant_model(tmp_path / "m.onnx", out, NAMES), providers=["CPUExecutionProvider"],
                       score_threshold=0.3, nms_iou=0.5)
    assert det._layout[0] == ("yolov5" if layout == "v5" else "yolov8")
    # image of the input size: the letterbox is the identity, boxes come back as given
    found = det.detect(np.zeros((IN_H, IN_W, 3), np.uint8))
    order = np.argsort(-found.scores)
    np.testing.assert_allclose(found.xyxy[order], xyxy(CANDIDATES[[0, 2]]), atol=1e-4)
    np.testing.assert_allclose(found.scores[order], [0.9, 0.6], atol=1e-6)
    assert found.cls[order].tolist() == [ObjectClass.CAR, ObjectClass.PEDESTRIAN]
    assert det.dropped_unmapped == 1 and det.unmapped_names == ("traffic light",)
    assert det.last_ms > 0 and len(det.last_breakdown_ms) == 3
    # the threshold applies: at 0.7 the person (0.6) goes; at 0.85 the NMS loser (0.8) still does not appear
    det.score_threshold = 0.7
    assert det.detect(np.zeros((IN_H, IN_W, 3), np.uint8)).cls.tolist() == [ObjectClass.CAR]
    # NMS is what removes the second car: with IoU threshold 0.95 it survives
    det.score_threshold, det.nms_iou = 0.3, 0.95
    assert sorted(det.detect(np.zeros((IN_H, IN_W, 3), np.uint8)).scores.round(3).tolist()) == [0.6, 0.8, 0.9]


def test_nms_is_class_aware(tmp_path):
    out = v8_output(True)
    out[0, 4:, 1] = [0.0, 0.0, 0.0, 0.0]
    out[0, 4 + 0, 1] = 0.8  # anchor 1 overlapping the car is now a person: both survive
    det = OnnxDetector(constant_model(tmp_path / "m.onnx", out, NAMES))
    found = det.detect(np.zeros((IN_H, IN_W, 3), np.uint8))
    assert sorted(found.cls.tolist()) == [ObjectClass.CAR, ObjectClass.PEDESTRIAN, ObjectClass.PEDESTRIAN]


def test_boxes_map_back_to_a_larger_image(tmp_path):
    """A 192 x 96 image letterboxes into 96 x 64 at scale 0.5 with 8 px of grey above and below."""
    det = OnnxDetector(constant_model(tmp_path / "m.onnx", v8_output(), NAMES))
    found = det.detect(np.zeros((96, 192, 3), np.uint8))
    order = np.argsort(-found.scores)
    expected = (xyxy(CANDIDATES[[0, 2]]) - [0, 8, 0, 8]) / 0.5
    np.testing.assert_allclose(found.xyxy[order], np.clip(expected, 0, [192, 96, 192, 96]), atol=1e-4)


def test_letterbox_round_trip_and_padding():
    rng = np.random.default_rng(3)
    image = np.zeros((317, 400, 3), np.uint8)  # r = 384 / 317: 484 x 384, 78 px grey each side
    x0, y0, x1, y1 = 120, 90, 260, 170
    image[y0:y1, x0:x1] = 255
    canvas, lb = letterbox(image, (640, 384))
    assert canvas.shape == (384, 640, 3)
    assert lb.pad_x > 0 and lb.pad_y == 0
    assert np.all(canvas[:, : int(lb.pad_x)] == 114) and np.all(canvas[:, 640 - int(lb.pad_x):] == 114)
    # the white rectangle's edges in the letterboxed image map back onto the drawn ones within a pixel
    ys, xs = np.nonzero(canvas[..., 0] > 127)
    found = lb.to_image(np.array([[xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]], float))
    np.testing.assert_allclose(found[0], [x0, y0, x1, y1], atol=1.0)
    # and the transform itself is an exact inverse
    boxes = rng.uniform(0, 300, (50, 4))
    np.testing.assert_allclose(lb.to_image(lb.to_input(boxes)), boxes, atol=1e-9)
    same, ident = letterbox(canvas, (640, 384))
    assert same is canvas and ident == Letterbox(1.0, 1.0, 0.0, 0.0)


def test_dynamic_input_takes_the_default_size(tmp_path):
    det = OnnxDetector(constant_model(tmp_path / "m.onnx", v8_output(), NAMES, dynamic_input=True))
    assert det.input_wh == (640, 384)
    det = OnnxDetector(tmp_path / "m.onnx", input_size=(600, 350))
    assert det.input_wh == (608, 352)


def test_names_metadata_mapping():
    names = parse_names("{0: 'person', 1: 'bicycle', 2: 'car', 3: 'motorcycle', 5: 'bus', 7: 'truck', 9: 'kite'}")
    table = class_table(names, 10)
    assert table[[0, 1, 2, 3, 5, 7]].tolist() == [ObjectClass.PEDESTRIAN, ObjectClass.CYCLIST, ObjectClass.CAR,
                                                  ObjectClass.MOTORCYCLE, ObjectClass.BUS, ObjectClass.TRUCK]
    assert table[[4, 6, 8, 9]].tolist() == [-1, -1, -1, -1]
    assert parse_names('["van", "Pedestrian"]') == {0: "van", 1: "Pedestrian"}
    assert class_table({0: "van", 1: "Pedestrian"}, 2).tolist() == [ObjectClass.VAN, ObjectClass.PEDESTRIAN]
    with pytest.raises(DetectorModelError):
        parse_names("not a dict")


def test_layout_errors_are_one_line(tmp_path):
    bad = constant_model(tmp_path / "bad.onnx", np.zeros((1, 300, 6)), NAMES)  # an end-to-end NMS export
    with pytest.raises(DetectorModelError, match=r"cannot read detector output of shape \[1, 300, 6\]") as err:
        OnnxDetector(bad)
    assert "\n" not in str(err.value)
    rows = np.concatenate([v8_output(False), np.zeros((1, 14, 8))], axis=1)  # [1, 20, 8] without names:
    v8t = constant_model(tmp_path / "v8t.onnx", rows)  # v8 with 4 classes, or v5 with 3?
    with pytest.raises(DetectorModelError, match="ambiguous"):
        OnnxDetector(v8t)
    assert OnnxDetector(v8t, names=["person", "bicycle", "car", "x"], layout="yolov8")._layout == ("yolov8", False)


def test_missing_and_corrupt_model_files(tmp_path):
    with pytest.raises(DetectorModelError, match="not found"):
        OnnxDetector(tmp_path / "nope.onnx")
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(b"\x08\x07garbage that is not a protobuf graph" * 10)
    with pytest.raises(DetectorModelError, match="cannot load detector model") as err:
        OnnxDetector(corrupt)
    assert "\n" not in str(err.value)


def test_providers_default_to_cpu_without_cuda(tmp_path, monkeypatch):
    import onnxruntime as ort

    path = constant_model(tmp_path / "m.onnx", v8_output(), NAMES)
    assert OnnxDetector(path).providers[-1] == "CPUExecutionProvider"
    if "CUDAExecutionProvider" not in ort.get_available_providers():
        assert OnnxDetector(path).providers == ["CPUExecutionProvider"]


def test_shipped_model_finds_the_cars_in_rendered_rsu_frames():
    """The RSU camera of red-light-runner and dense-intersection: cars and vans within 80 m that
    are at least half visible and 12 px wide are found (IoU >= 0.5), box bottom within 1.5 px (median)."""
    from v2i.sim.camera import rsu_camera
    from v2i.sim.render import SceneRenderer
    from v2i.sim.scenario import load_scenario
    from v2i.sim.world import World

    assert SHIPPED_MODEL.is_file() and SHIPPED_MODEL.stat().st_size <= 10e6
    det = OnnxDetector(providers=["CPUExecutionProvider"])
    found = total = 0
    bottom_err_px = []
    for name, times in (("red-light-runner", (5.0, 7.0, 9.0, 11.0)), ("dense-intersection", (4.0, 10.0, 16.0, 22.0))):
        world = World(load_scenario(name))
        renderer, camera = SceneRenderer(world, seed=0), rsu_camera(world.scenario.rsu)
        for t in times:
            frame = renderer.render(camera, t)
            lab = frame.labels
            wanted = (np.isin(lab.cls, [ObjectClass.CAR, ObjectClass.VAN]) & (lab.visible >= 0.5)
                      & (lab.range_m < 80.0) & (lab.xyxy[:, 2] - lab.xyxy[:, 0] >= 12.0))
            dets = det.detect(frame.image)
            vehicles = dets.xyxy[np.isin(dets.cls, [ObjectClass.CAR, ObjectClass.VAN])]
            for box in lab.xyxy[wanted]:
                total += 1
                if len(vehicles) == 0:
                    continue
                lt, rb = np.maximum(vehicles[:, :2], box[:2]), np.minimum(vehicles[:, 2:], box[2:])
                inter = np.prod(np.clip(rb - lt, 0, None), axis=1)
                iou = inter / (np.prod(vehicles[:, 2:] - vehicles[:, :2], axis=1) + np.prod(box[2:] - box[:2]) - inter)
                if iou.max() >= 0.5:
                    found += 1
                    bottom_err_px.append(abs(vehicles[np.argmax(iou), 3] - box[3]))
    assert total >= 15
    assert found / total >= 0.85, f"found {found} of {total} cars"
    assert np.median(bottom_err_px) <= 1.5


def test_non_finite_and_empty_boxes_from_a_model_are_dropped_and_counted(tmp_path):
    """A model's output is input too: NaN / inf coordinates, zero or negative sizes and boxes
    wholly off the image never become detections (they did: a NaN box came through NMS)."""
    out = np.zeros((1, 4 + 2, 8), np.float32)
    out[0, :4, :] = np.array([48.0, 32.0, 10.0, 8.0])[:, None]
    out[0, 4, :] = 0.9
    out[0, 0, 0], out[0, 1, 1], out[0, 2, 2], out[0, 3, 3] = np.nan, np.inf, 0.0, -4.0
    out[0, 0, 4] = 1e6  # centred far off the image
    out[0, 4, 5] = np.nan  # a NaN score: below any threshold
    det = OnnxDetector(constant_model(tmp_path / "m.onnx", out, names="{0: 'car', 1: 'person'}"))
    d = det.detect(np.zeros((IN_H, IN_W, 3), np.uint8))
    assert np.isfinite(d.xyxy).all() and np.isfinite(d.scores).all()
    assert len(d) == 1 and np.allclose(d.xyxy[0], [43.0, 28.0, 53.0, 36.0])  # the two valid rows, one after NMS
    assert det.dropped_invalid == 5
