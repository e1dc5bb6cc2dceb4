"""A COCO YOLOv8n export through ``--model``: 1x3x640x640 in, 1x84x8400 out, COCO ids to v2i classes.

The graph is built here with YOLOv8n's shapes and random weights (three strided levels of
80x80, 40x40 and 20x20 cells = 8400 anchors, a 1x1 head of 4 box + 80 class channels on each,
sigmoid class scores, no objectness). Its class logits sit near -9 (YOLOv8 initialises its class
bias near there too), so random anchors stay far below any threshold, and a constant planted on
a few anchors makes known boxes and classes come out: a layout read wrongly (channels last, a
fifth objectness channel, class ids off by one, the letterbox not undone) moves or loses them.
"""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from v2i.perception.detector import Detections2D, OnnxDetector
from rsu_service.config import RsuConfig
from rsu_service.source import open_perception
from schemas.classes import ObjectClass

COCO80 = ["person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat", "traffic light",
          "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog", "horse", "sheep", "cow",
          "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella", "handbag", "tie", "suitcase", "frisbee",
          "skis", "snowboard", "sports ball", "kite", "baseball bat", "baseball glove", "skateboard", "surfboard",
          "tennis racket", "bottle", "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple",
          "sandwich", "orange", "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch",
          "potted plant", "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote", "keyboard",
          "cell phone", "microwave", "oven", "toaster", "sink", "refrigerator", "book", "clock", "vase", "scissors",
          "teddy bear", "hair drier", "toothbrush"]
ULTRALYTICS_NAMES = repr(dict(enumerate(COCO80)))  # the metadata an ultralytics export writes
INPUT_PX = 640
ANCHORS = 80 * 80 + 40 * 40 + 20 * 20  # 8400
CLASS_BIAS = -9.0
BUS, PERSON, TRUCK, TRAFFIC_LIGHT, AIRPLANE = 5, 0, 7, 9, 4

# Planted anchors: (anchor, cx, cy, w, h in letterboxed input px, COCO class, class logit above the bias).
# sigmoid(-9 + 11.2) = 0.90, sigmoid(-9 + 10.4) = 0.80, sigmoid(-9 + 9.85) = 0.70, sigmoid(-9 + 9.4) = 0.60
PLANTS = [
    (1234, 330.0, 420.0, 300.0, 190.0, BUS, 11.2),  # the bus
    (6500, 334.0, 424.0, 296.0, 186.0, BUS, 10.4),  # the same bus from another level: NMS removes it
    (8000, 300.0, 440.0, 40.0, 110.0, PERSON, 9.85),  # a pedestrian in front of it: other class, kept
    (7777, 110.0, 500.0, 80.0, 60.0, TRUCK, 9.4),  # a truck cut by the image's left edge (x0 in the padding)
    (3000, 500.0, 150.0, 20.0, 50.0, TRAFFIC_LIGHT, 12.0),  # not a v2i class: dropped and counted
    (5000, 200.0, 200.0, 30.0, 30.0, AIRPLANE, 0.0),  # class 4 below the threshold: read as 5 it would be a bus
]


def _conv(name, x, cin, cout, stride, rng, nodes, inits, bias=0.0, std=0.05):
    w = rng.normal(0.0, std, (cout, cin, 3 if stride > 1 else 1, 3 if stride > 1 else 1)).astype(np.float32)
    b = np.full(cout, bias, np.float32)
    inits += [numpy_helper.from_array(w, f"{name}.w"), numpy_helper.from_array(b, f"{name}.b")]
    pads = [1, 1, 1, 1] if stride > 1 else [0, 0, 0, 0]
    nodes.append(helper.make_node("Conv", [x, f"{name}.w", f"{name}.b"], [name], strides=[stride, stride], pads=pads))
    return name


def yolov8n_shaped(path, names: str | None, seed: int = 0) -> str:
    """A graph images [1, 3, 640, 640] -> output0 [1, 84, 8400] with random weights and the PLANTS."""
    rng = np.random.default_rng(seed)
    nodes, inits = [], []
    x = _conv("stem", "images", 3, 8, 8, rng, nodes, inits)  # 80 x 80
    nodes.append(helper.make_node("Relu", [x], ["p3"]))
    nodes.append(helper.make_node("Relu", [_conv("down4", "p3", 8, 8, 2, rng, nodes, inits)], ["p4"]))  # 40 x 40
    nodes.append(helper.make_node("Relu", [_conv("down5", "p4", 8, 8, 2, rng, nodes, inits)], ["p5"]))  # 20 x 20
    shape = numpy_helper.from_array(np.array([1, 84, -1], np.int64), "flat")
    inits.append(shape)
    levels = []
    for level in ("p3", "p4", "p5"):
        bias = np.r_[np.zeros(4), np.full(80, CLASS_BIAS)].astype(np.float32)
        head = _conv(f"head_{level}", level, 8, 84, 1, rng, nodes, inits, std=0.02)
        inits[-1] = numpy_helper.from_array(bias, f"head_{level}.b")
        nodes.append(helper.make_node("Reshape", [head, "flat"], [f"{level}_flat"]))
        levels.append(f"{level}_flat")
    nodes.append(helper.make_node("Concat", levels, ["raw"], axis=2))  # [1, 84, 8400]
    plant = np.zeros((1, 84, ANCHORS), np.float32)
    for anchor, cx, cy, w, h, cls, logit in PLANTS:
        plant[0, :4, anchor] = cx, cy, w, h
        plant[0, 4 + cls, anchor] = logit
    inits.append(numpy_helper.from_array(plant, "plant"))
    nodes.append(helper.make_node("Add", ["raw", "plant"], ["planted"]))
    for name, start, end in (("box", 0, 4), ("logits", 4, 84)):
        s, e, a = (numpy_helper.from_array(np.array([v], np.int64), f"{name}.{k}")
                   for k, v in (("s", start), ("e", end), ("a", 1)))
        inits += [s, e, a]
        nodes.append(helper.make_node("Slice", ["planted", f"{name}.s", f"{name}.e", f"{name}.a"], [name]))
    nodes.append(helper.make_node("Sigmoid", ["logits"], ["scores"]))
    nodes.append(helper.make_node("Concat", ["box", "scores"], ["output0"], axis=1))
    graph = helper.make_graph(
        nodes, "yolov8n-shaped",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, INPUT_PX, INPUT_PX])],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, 84, ANCHORS])], initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    if names is not None:
        model.metadata_props.add(key="names", value=names)
    onnx.checker.check_model(model, full_check=True)
    onnx.save(model, str(path))
    return str(path)


def expected_boxes(width: int, height: int) -> dict[int, np.ndarray]:
    """The kept plants' boxes in an image of ``width`` x ``height`` px, by COCO class: the letterbox
    scale r = 640 / max(W, H), the pad centred, then clipped to the image."""
    r = INPUT_PX / max(width, height)
    new_w, new_h = round(width * r), round(height * r)
    pad = np.array([(INPUT_PX - new_w) // 2, (INPUT_PX - new_h) // 2] * 2, float)
    scale = np.array([new_w / width, new_h / height] * 2)
    out = {}
    for _, cx, cy, w, h, cls, _ in (PLANTS[0], PLANTS[2], PLANTS[3]):
        box = (np.array([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2]) - pad) / scale
        out[cls] = np.clip(box, 0, [width, height, width, height])
    return out


def check_detections(found, dropped_unmapped: int, width: int, height: int) -> None:
    """The bus, the person and the truck (in that score order) where the plants put them."""
    assert found.xyxy.shape == (3, 4) and found.scores.shape == (3,) and found.cls.shape == (3,)
    order = np.argsort(-found.scores)
    assert found.cls[order].tolist() == [ObjectClass.BUS, ObjectClass.PEDESTRIAN, ObjectClass.TRUCK]
    np.testing.assert_allclose(found.scores[order], [0.90, 0.70, 0.60], atol=0.02)
    want = expected_boxes(width, height)
    for row, cls in zip(order, (BUS, PERSON, TRUCK)):
        np.testing.assert_allclose(found.xyxy[row], want[cls], atol=1.0)
    assert (found.xyxy >= 0).all() and (found.xyxy[:, [0, 2]] <= width).all() and (found.xyxy[:, [1, 3]] <= height).all()
    assert dropped_unmapped == 1  # the traffic light


@pytest.mark.parametrize("names", [ULTRALYTICS_NAMES, None], ids=["names-metadata", "no-metadata"])
def test_a_yolov8n_export_on_a_tall_street_photo(tmp_path, names):
    """810 x 1080 px (the size of the street photo the shipped model failed on): letterboxed to
    480 x 640 with 80 px of grey left and right; the boxes come back in the photo's pixels."""
    detector = OnnxDetector(yolov8n_shaped(tmp_path / "yolov8n.onnx", names), providers=["CPUExecutionProvider"],
                            score_threshold=0.25)
    assert detector.input_wh == (INPUT_PX, INPUT_PX) and detector._layout == ("yolov8", True)
    photo = np.random.default_rng(1).integers(0, 256, (1080, 810, 3), dtype=np.uint8)
    found = detector.detect(photo)
    check_detections(found, detector.dropped_unmapped, 810, 1080)
    assert found.xyxy[found.cls == ObjectClass.TRUCK][0, 0] == 0.0  # cut by the edge, clipped there


def test_model_flag_runs_a_yolov8n_export_into_map_objects(tmp_path):
    """``v2i rsu --source video --model yolov8n.onnx --calibration cam.calib.json`` opens its
    perception this way: the model's boxes on a 640 x 384 frame (pad 128 px above and below),
    each taken to the map as an object of the mapped class."""
    from v2i.perception.calibration import calibration_path

    config = RsuConfig(source="video", video=str(tmp_path), model=yolov8n_shaped(tmp_path / "m.onnx", ULTRALYTICS_NAMES),
                       calibration=str(calibration_path("red-light-runner")), score_threshold=0.25)
    perception = open_perception(config, site=None)
    frame = np.random.default_rng(2).integers(0, 256, (384, 640, 3), dtype=np.uint8)
    dropped_before = perception.detector.dropped_unmapped  # open() ran the detector once on a blank frame
    objects, detector_ms = perception.perceive(frame)
    found = Detections2D(*perception.last_detections)
    check_detections(found, perception.detector.dropped_unmapped - dropped_before, 640, 384)
    assert detector_ms > 0
    assert sorted(objects.cls.tolist()) == sorted([ObjectClass.BUS, ObjectClass.PEDESTRIAN, ObjectClass.TRUCK])
    assert np.isfinite(objects.xy).all()
