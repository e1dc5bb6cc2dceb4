"""Image object detector on ONNX Runtime: YOLO-style exports in, boxes in image pixels out.

Output layouts read (batch 1; ``nc`` = number of classes, ``A`` = number of anchors/cells):

- YOLOv8 (ultralytics ``export format=onnx``, and the shipped model): ``[1, 4+nc, A]`` or its
  transpose ``[1, A, 4+nc]``; per anchor cx, cy, w, h in letterboxed input pixels, then one
  score per class (already sigmoid), no objectness. score = max over classes.
- YOLOv5 (``export.py --include onnx``): ``[1, A, 5+nc]``; cx, cy, w, h, objectness, class
  probabilities; score = objectness * class probability.

How the layout is told apart: a metadata entry ``layout`` (``yolov8`` / ``yolov5``) wins;
otherwise ``nc`` from the ``names`` metadata decides (the axis of length 4+nc is the channel
axis of a v8 model; a last axis of 5+nc is v5). Without names only a channel-first v8 model is
unambiguous (A > channels); otherwise pass ``names=`` or ``layout=``. With dynamic output dims
the layout is resolved on the first output.

Pre-processing: letterbox to the model's input size (read from its input shape; dynamic dims
take ``input_size``, default 640 x 384, rounded up to stride 32), grey 114 padding centred, BGR
-> RGB, / 255. Post-processing: score threshold, class-aware NMS (``cv2.dnn.NMSBoxesBatched``),
boxes back to the original image's pixels. Class names (metadata ``names``, ultralytics style
``{0: 'person', ...}``) map to ``ObjectClass`` by name; detections of other classes are dropped
and counted (``dropped_unmapped``), so a COCO YOLOv8n export works unchanged.

The shipped model (``SHIPPED_MODEL``) is trained by ``tools/train_detector.py`` on frames the
renderer (``v2i.sim.render``) draws of the bundled scenarios, and on nothing else: it is for those
scenes. On real camera images it is no detector (on a street photo of a city bus with
pedestrians it found 11 boxes, none of them the bus). For real images pass a model trained on
real images, e.g. a COCO YOLOv8n export (ultralytics ``yolo export model=yolov8n.pt
format=onnx``: input [1, 3, 640, 640], output [1, 84, 8400], names metadata), with ``v2i rsu
--model``; ``tests/unit/test_detector_yolov8n.py`` runs that layout through the same path.
"""

from __future__ import annotations

import ast
import json
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort

from schemas.classes import ObjectClass
from v2i.core.files import FileMissing, FileRefused, MiB, read_bounded

SHIPPED_MODEL = Path(__file__).with_name("models") / "v2i-det.onnx"
# A model file, read whole and handed to ONNX Runtime as bytes: the shipped one is 3.4 MB, the largest
# YOLOv8 export (x) ~270 MB. (A model with its weights in external data files is not read.)
MODEL_LIMIT_BYTES = 512 * MiB
DEFAULT_INPUT_WH = (640, 384)
STRIDE_PX = 32
PAD_VALUE = 114
MAX_CANDIDATES = 4096  # highest-scoring candidates kept before NMS

CLASS_BY_NAME = {
    "person": ObjectClass.PEDESTRIAN, "pedestrian": ObjectClass.PEDESTRIAN,
    "bicycle": ObjectClass.CYCLIST, "cyclist": ObjectClass.CYCLIST,
    "car": ObjectClass.CAR, "van": ObjectClass.VAN, "truck": ObjectClass.TRUCK, "bus": ObjectClass.BUS,
    "motorcycle": ObjectClass.MOTORCYCLE, "motorbike": ObjectClass.MOTORCYCLE,
}
# COCO-80 indices of the classes above, for an export that lost its names metadata
COCO_NAMES = {0: "person", 1: "bicycle", 2: "car", 3: "motorcycle", 5: "bus", 7: "truck"}


class DetectorModelError(ValueError):
    """A model file that cannot be loaded or whose output layout cannot be read (one-line message)."""


@dataclass(frozen=True)
class Detections2D:
    """N boxes in one image: ``xyxy`` (N, 4) float px (x0, y0, x1, y1) in the input image,
    ``scores`` (N,) float in [0, 1], ``cls`` (N,) int64 ``ObjectClass`` codes."""

    xyxy: np.ndarray
    scores: np.ndarray
    cls: np.ndarray

    def __len__(self) -> int:
        return len(self.scores)

    @classmethod
    def empty(cls) -> "Detections2D":
        return cls(np.zeros((0, 4)), np.zeros(0), np.zeros(0, dtype=np.int64))


@dataclass(frozen=True)
class Letterbox:
    """Image -> letterboxed input: u_in = u * sx + pad_x, v_in = v * sy + pad_y (px).

    sx, sy are the realised per-axis scales (resized size / original size), so the inverse
    u = (u_in - pad_x) / sx is exact for the pixels the resize produced.
    """

    sx: float
    sy: float
    pad_x: float
    pad_y: float

    def to_input(self, xyxy: np.ndarray) -> np.ndarray:
        """Boxes (N, 4) image px -> letterboxed input px."""
        return xyxy * [self.sx, self.sy, self.sx, self.sy] + [self.pad_x, self.pad_y, self.pad_x, self.pad_y]

    def to_image(self, xyxy: np.ndarray) -> np.ndarray:
        """Boxes (N, 4) letterboxed input px -> image px."""
        return (xyxy - [self.pad_x, self.pad_y, self.pad_x, self.pad_y]) / [self.sx, self.sy, self.sx, self.sy]


def letterbox(image: np.ndarray, size_wh: tuple[int, int]) -> tuple[np.ndarray, Letterbox]:
    """Resize (H, W, 3) keeping aspect into ``size_wh``, pad centred with grey 114.

    r = min(W_in / W, H_in / H); resized (round(W r), round(H r)); pad split evenly (floor left/top).
    """
    h, w = image.shape[:2]
    w_in, h_in = size_wh
    r = min(w_in / w, h_in / h)
    new_w, new_h = min(w_in, round(w * r)), min(h_in, round(h * r))
    resized = image if (new_w, new_h) == (w, h) else cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
    left, top = (w_in - new_w) // 2, (h_in - new_h) // 2
    if (new_w, new_h) != (w_in, h_in):
        resized = cv2.copyMakeBorder(resized, top, h_in - new_h - top, left, w_in - new_w - left,
                                     cv2.BORDER_CONSTANT, value=(PAD_VALUE,) * 3)
    return resized, Letterbox(new_w / w, new_h / h, float(left), float(top))


def parse_names(text: str) -> dict[int, str]:
    """Class names from metadata: ultralytics' ``{0: 'person', ...}``, JSON dict or list."""
    try:
        value = ast.literal_eval(text)
    except (ValueError, SyntaxError):
        try:
            value = json.loads(text)
        except ValueError:
            raise DetectorModelError(f"cannot parse the model's 'names' metadata: {text[:80]!r}") from None
    if isinstance(value, (list, tuple)):
        value = dict(enumerate(value))
    if not isinstance(value, dict):
        raise DetectorModelError(f"the model's 'names' metadata is not a dict or list: {text[:80]!r}")
    return {int(k): str(v) for k, v in value.items()}


def class_table(names: dict[int, str], nc: int) -> np.ndarray:
    """(nc,) int64: ObjectClass code of each model class, -1 where the name maps to none."""
    table = np.full(nc, -1, dtype=np.int64)
    for i, name in names.items():
        if 0 <= i < nc and name.strip().lower() in CLASS_BY_NAME:
            table[i] = int(CLASS_BY_NAME[name.strip().lower()])
    return table


def resolve_layout(shape: tuple, nc: int | None, layout_hint: str | None) -> tuple[str, bool]:
    """(layout 'yolov8' | 'yolov5', channels_first) for an output of ``shape`` (3 ints)."""
    if len(shape) != 3 or shape[0] != 1 or not all(isinstance(d, int) and d > 0 for d in shape):
        raise DetectorModelError(f"cannot read detector output of shape {list(shape)}: expected [1, C, A] or [1, A, C]")
    _, d1, d2 = shape
    hint = (layout_hint or "").lower()
    if nc is not None:
        fits = [("yolov8", True)] if d1 == 4 + nc and hint != "yolov5" else []
        fits += [("yolov8", False)] if d2 == 4 + nc and hint != "yolov5" else []
        fits += [("yolov5", False)] if d2 == 5 + nc and hint != "yolov8" else []
        if len(fits) > 1:  # square-ish outputs: anchors outnumber channels
            fits = [f for f in fits if f[1] == (d2 > d1)] or fits
        if fits:
            return fits[0]
        raise DetectorModelError(f"cannot read detector output of shape {list(shape)} with {nc} class names: "
                                 f"expected [1, {4 + nc}, A], [1, A, {4 + nc}] (YOLOv8) or [1, A, {5 + nc}] (YOLOv5)")
    if hint in ("yolov8", "yolov5"):
        return hint, hint == "yolov8" and d2 > d1
    if d2 > d1 > 4:
        return "yolov8", True
    raise DetectorModelError(f"detector output {list(shape)} is ambiguous without 'names' metadata: "
                             "pass names= or layout='yolov8'/'yolov5'")


def decode(output: np.ndarray, layout: str, channels_first: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw output (1, C, A) or (1, A, C) -> cxcywh (A, 4), best score (A,), best class (A,)."""
    rows = output[0].T if channels_first else output[0]  # (A, C), a view
    if layout == "yolov8":
        scores = rows[:, 4:]
        best = scores.argmax(axis=1)
        conf = scores[np.arange(len(rows)), best]
    else:  # score = objectness * P(class | object)
        probs = rows[:, 5:]
        best = probs.argmax(axis=1)
        conf = rows[:, 4] * probs[np.arange(len(rows)), best]
    return rows[:, :4], conf, best


def nms_per_class(xyxy: np.ndarray, scores: np.ndarray, classes: np.ndarray, iou: float) -> np.ndarray:
    """Indices kept by class-aware NMS (``cv2.dnn.NMSBoxesBatched`` on x, y, w, h boxes), best first."""
    if len(scores) == 0:
        return np.zeros(0, dtype=np.int64)
    xywh = np.column_stack([xyxy[:, :2], xyxy[:, 2:] - xyxy[:, :2]]).astype(np.float64)
    keep = cv2.dnn.NMSBoxesBatched(xywh, scores.astype(np.float32), classes.astype(np.int32), 0.0, float(iou))
    return np.asarray(keep, dtype=np.int64).reshape(-1)


def _providers(pinned) -> list:
    if pinned is not None:
        return list(pinned)
    available = ort.get_available_providers()
    return (["CUDAExecutionProvider"] if "CUDAExecutionProvider" in available else []) + ["CPUExecutionProvider"]


def _open_session(path: Path, providers, threads: int | None) -> ort.InferenceSession:
    try:
        model = read_bounded(path, MODEL_LIMIT_BYTES, "detector model")
    except FileMissing:
        raise DetectorModelError(f"detector model not found: {path}") from None
    except FileRefused as exc:
        raise DetectorModelError(str(exc)) from None
    options = ort.SessionOptions()
    if threads:
        options.intra_op_num_threads = int(threads)
    try:
        return ort.InferenceSession(model, options, providers=_providers(providers))
    except Exception as exc:  # onnxruntime raises its own Fail / InvalidProtobuf / InvalidGraph types
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DetectorModelError(f"cannot load detector model {path}: {first}") from None


def _as_names(names) -> dict[int, str]:
    """Names given as metadata text, a list or a dict -> {index: name}."""
    if isinstance(names, str):
        return parse_names(names)
    if isinstance(names, (list, tuple)):
        return dict(enumerate(map(str, names)))
    return {int(k): str(v) for k, v in dict(names).items()}


def _input_size(shape, input_size_wh) -> tuple[int, int]:
    """(W, H) from an input shape [1, 3, H, W]; dynamic dims take ``input_size_wh`` rounded up to stride 32."""
    if len(shape) != 4:
        raise DetectorModelError(f"detector input shape {list(shape)} is not [1, 3, H, W]")
    h, w = shape[2], shape[3]
    if isinstance(h, int) and isinstance(w, int) and h > 0 and w > 0:
        return w, h
    w_req, h_req = input_size_wh or DEFAULT_INPUT_WH
    return -(-int(w_req) // STRIDE_PX) * STRIDE_PX, -(-int(h_req) // STRIDE_PX) * STRIDE_PX


class OnnxDetector:
    """A YOLOv8- or YOLOv5-layout ONNX detector (see the module docstring).

    ``model_path`` None = the shipped model. ``providers`` None = CUDA first when onnxruntime
    has it, then CPU; a list pins them. ``threads`` sets ``intra_op_num_threads`` (None: ORT's
    default). ``names``/``layout`` override the model's metadata. ``input_size`` (W, H) applies
    to models with dynamic input dims only. ``last_ms`` is the wall time of the last ``detect``
    (pre-processing, inference and post-processing); ``last_breakdown_ms`` splits it.
    """

    def __init__(self, model_path=None, providers=None, score_threshold: float = 0.3, nms_iou: float = 0.5,
                 threads: int | None = None, names=None, layout: str | None = None, input_size=None):
        self.model_path = Path(model_path) if model_path is not None else SHIPPED_MODEL
        self.session = _open_session(self.model_path, providers, threads)
        self.score_threshold = float(score_threshold)
        self.nms_iou = float(nms_iou)
        inp = self.session.get_inputs()[0]
        self._input_name = inp.name
        self._input_dtype = np.float16 if "float16" in inp.type else np.float32
        self.input_wh = _input_size(inp.shape, input_size)
        meta = self.session.get_modelmeta().custom_metadata_map
        self._layout_hint = layout or meta.get("layout")
        if names is None and "names" in meta:
            names = meta["names"]
        self.names = _as_names(names) if names is not None else None
        self._layout: tuple[str, bool] | None = None
        self._classes: np.ndarray | None = None
        out_shape = tuple(self.session.get_outputs()[0].shape)
        if all(isinstance(d, int) for d in out_shape):
            self._bind_layout(out_shape)  # static output: fail now, not at the first image
        self.unmapped_names = tuple(sorted(n for n in (self.names or {}).values()
                                           if n.strip().lower() not in CLASS_BY_NAME))
        self.dropped_unmapped = 0
        self.dropped_invalid = 0  # candidates above the threshold with a non-finite or empty box
        self.last_ms = float("nan")
        self.last_breakdown_ms = (float("nan"),) * 3

    @property
    def providers(self) -> list[str]:
        return self.session.get_providers()

    def _bind_layout(self, shape: tuple) -> None:
        nc = len(self.names) if self.names is not None else None
        if nc is not None and self.names and max(self.names) >= nc:
            nc = max(self.names) + 1
        layout, channels_first = resolve_layout(shape, nc, self._layout_hint)
        n_classes = shape[1 if channels_first else 2] - (4 if layout == "yolov8" else 5)
        names = self.names if self.names is not None else (COCO_NAMES if n_classes == 80 else {})
        if self.names is None and n_classes != 80:
            raise DetectorModelError(f"detector output {list(shape)} has {n_classes} classes and no 'names' "
                                     "metadata to map them: pass names=")
        self._layout = (layout, channels_first)
        self._classes = class_table(names, n_classes)

    def preprocess(self, image_bgr: np.ndarray) -> tuple[np.ndarray, Letterbox]:
        """(H, W, 3) uint8 BGR -> input tensor (1, 3, H_in, W_in) RGB in [0, 1] and its letterbox."""
        if image_bgr.ndim != 3 or image_bgr.shape[2] != 3:
            raise ValueError(f"detect() wants an (H, W, 3) BGR image, got shape {image_bgr.shape}")
        canvas, lb = letterbox(image_bgr, self.input_wh)
        blob = cv2.dnn.blobFromImage(canvas, scalefactor=1.0 / 255.0, swapRB=True)  # HWC BGR -> NCHW RGB
        return blob.astype(self._input_dtype, copy=False), lb

    def postprocess(self, output: np.ndarray, lb: Letterbox, image_hw: tuple[int, int]) -> Detections2D:
        """Raw output -> thresholded, NMS-ed boxes in image px; unmapped classes dropped and counted."""
        if self._layout is None:
            self._bind_layout(tuple(int(d) for d in output.shape))
        cxcywh, conf, best = decode(output, *self._layout)
        # a model's output is input too: non-finite or empty boxes are dropped and counted
        valid = np.isfinite(cxcywh).all(axis=1) & (cxcywh[:, 2] > 0) & (cxcywh[:, 3] > 0)
        above = conf >= self.score_threshold  # False for NaN
        self.dropped_invalid += int(np.count_nonzero(above & ~valid))
        idx = np.flatnonzero(above & valid)
        if len(idx) > MAX_CANDIDATES:
            idx = idx[np.argpartition(conf[idx], -MAX_CANDIDATES)[-MAX_CANDIDATES:]]
        c = cxcywh[idx].astype(np.float64)
        xyxy = np.column_stack([c[:, :2] - c[:, 2:] / 2, c[:, :2] + c[:, 2:] / 2])  # (cx -/+ w/2, cy -/+ h/2)
        kept = nms_per_class(xyxy, conf[idx], best[idx], self.nms_iou)
        cls = self._classes[best[idx][kept]]
        mapped = cls >= 0
        self.dropped_unmapped += int(np.count_nonzero(~mapped))
        keep = kept[mapped]
        boxes = lb.to_image(xyxy[keep])
        h, w = image_hw
        boxes = np.clip(boxes, 0.0, [w, h, w, h])
        inside = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])  # a box wholly off the image is none
        self.dropped_invalid += int(np.count_nonzero(~inside))
        return Detections2D(boxes[inside], conf[idx][keep][inside].astype(np.float64), cls[mapped][inside])

    def detect(self, image_bgr: np.ndarray) -> Detections2D:
        """Boxes of the mapped classes in ``image_bgr`` (H, W, 3) uint8 BGR; sets ``last_ms``."""
        t0 = time.perf_counter()
        blob, lb = self.preprocess(image_bgr)
        t1 = time.perf_counter()
        output = self.session.run(None, {self._input_name: blob})[0]
        t2 = time.perf_counter()
        dets = self.postprocess(np.asarray(output, dtype=np.float32), lb, image_bgr.shape[:2])
        t3 = time.perf_counter()
        self.last_breakdown_ms = ((t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3)
        self.last_ms = (t3 - t0) * 1e3
        return dets
