"""Training samples for ``tools/train_detector.py`` (numpy + OpenCV, no torch): the rendered-frame
cache, random augmented crops and their CenterNet-style targets at stride 4.

Cache folder: ``images.npy`` (N, 384, 640, 3) uint8 BGR (memory-mapped), ``labels.npz`` with one
row per labelled box: ``frame`` (M,) int, ``xyxy`` (M, 4) px, ``cls`` (M,) ObjectClass code,
``visible`` (M,) fraction, ``range_m`` (M,); ``meta.json`` says how it was rendered.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

CLASS_NAMES = ("car", "van", "truck", "bus", "pedestrian", "cyclist", "motorcycle")  # = ObjectClass 1..7
STRIDE = 4
INPUT_HW = (384, 640)
MIN_BOX_PX = (2.0, 3.0)  # smaller boxes (w, h) are ignored, not targets
MIN_KEPT_AREA = 0.2  # a box cut by the crop to less than this share of its area is ignored (the rest are
# positives with the clipped box, as the renderer labels bodies cut by the frame's edge)
SIGMA_FRACTION, SIGMA_MIN_CELLS = 0.12, 0.6  # heat Gaussian sigma = max(0.6 cells, 0.12 box size)
REG_MIN_HEAT = 0.4  # cells regressing a box: heat >= this (and the peak cell)


@dataclass(frozen=True)
class Cache:
    images: np.ndarray  # (N, H, W, 3) uint8 BGR
    boxes: tuple  # per frame: (xyxy (K, 4), cls (K,), visible (K,), range_m (K,))


def load_cache(folder: Path) -> Cache:
    images = np.load(Path(folder) / "images.npy", mmap_mode="r")
    lab = np.load(Path(folder) / "labels.npz")
    order = np.argsort(lab["frame"], kind="stable")
    starts = np.searchsorted(lab["frame"][order], np.arange(len(images) + 1))
    cols = [lab[k][order] for k in ("xyxy", "cls", "visible", "range_m")]
    boxes = tuple(tuple(c[starts[i]:starts[i + 1]] for c in cols) for i in range(len(images)))
    return Cache(images, boxes)


def photometric(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Contrast/brightness/colour gain, then maybe blur and sensor noise; (H, W, 3) uint8 -> float32."""
    out = img.astype(np.float32) * (rng.uniform(0.75, 1.25) * rng.uniform(0.92, 1.08, 3)) + rng.uniform(-20, 20)
    if rng.random() < 0.2:
        out = cv2.GaussianBlur(out, (3, 3), rng.uniform(0.4, 1.0))
    if rng.random() < 0.5:
        out += rng.standard_normal(out.shape, dtype=np.float32) * np.float32(rng.uniform(1.0, 5.0))
    return np.clip(out, 0, 255)


class CropSampler:
    """Random crops (H_c, W_c) of cached frames, scaled, flipped, photometrically jittered."""

    def __init__(self, cache: Cache, crop_hw=(224, 352), min_visible: float = 0.3):
        self.cache, self.crop_hw, self.min_visible = cache, tuple(crop_hw), min_visible
        cls = np.concatenate([b[1][b[2] >= min_visible] for b in cache.boxes])
        counts = np.bincount(cls, minlength=len(CLASS_NAMES) + 1).astype(float)
        self.class_weight = 1.0 / np.sqrt(np.maximum(counts, 1.0))  # (nc + 1,) by ObjectClass code: w = n_c^-1/2

    def crop(self, i: int, rng: np.random.Generator):
        """Frame ``i`` -> image (H_c, W_c, 3) float32 BGR, boxes (K, 4), cls (K,), positive (K,) bool."""
        xyxy, cls, visible, _ = self.cache.boxes[i]
        img = np.asarray(self.cache.images[i])
        scale = float(np.exp(rng.uniform(np.log(0.5), np.log(1.5)))) if rng.random() < 0.6 else 1.0
        if scale != 1.0:
            img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
        boxes = xyxy * scale
        ch, cw = self.crop_hw
        h, w = img.shape[:2]
        good = np.flatnonzero((visible >= self.min_visible) & (cls >= 1))
        if len(good) and rng.random() < 0.7:  # centre the crop near a target, rare classes more often
            p = self.class_weight[cls[good]]
            bx = boxes[rng.choice(good, p=p / p.sum())]
            cx, cy = (bx[0] + bx[2]) / 2 + rng.uniform(-0.4, 0.4) * cw, (bx[1] + bx[3]) / 2 + rng.uniform(-0.4, 0.4) * ch
        else:
            cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        x0 = int(np.clip(cx - cw / 2, min(0, w - cw), max(0, w - cw)))
        y0 = int(np.clip(cy - ch / 2, min(0, h - ch), max(0, h - ch)))
        canvas = np.full((ch, cw, 3), 114, np.uint8)
        sx0, sy0 = max(x0, 0), max(y0, 0)
        sx1, sy1 = min(x0 + cw, w), min(y0 + ch, h)
        canvas[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0] = img[sy0:sy1, sx0:sx1]
        boxes = boxes - [x0, y0, x0, y0]
        clipped = np.clip(boxes, 0, [sx1 - x0, sy1 - y0, sx1 - x0, sy1 - y0])
        area = lambda b: np.clip(b[:, 2] - b[:, 0], 0, None) * np.clip(b[:, 3] - b[:, 1], 0, None)  # noqa: E731
        kept = area(clipped) / np.maximum(area(boxes), 1e-9)
        wh = clipped[:, 2:] - clipped[:, :2]
        present = area(clipped) > 0
        positive = (visible >= self.min_visible) & (kept >= MIN_KEPT_AREA) & np.all(wh >= MIN_BOX_PX, axis=1) & (cls >= 1)
        if rng.random() < 0.5:  # horizontal flip
            canvas = canvas[:, ::-1]
            clipped = np.column_stack([cw - clipped[:, 2], clipped[:, 1], cw - clipped[:, 0], clipped[:, 3]])
        return photometric(np.ascontiguousarray(canvas), rng), clipped[present], cls[present], positive[present]

    def batch(self, rng: np.random.Generator, size: int) -> dict:
        """Images (B, 3, H_c, W_c) float32 RGB in [0, 1] and targets (see ``targets``)."""
        ch, cw = self.crop_hw
        images = np.empty((size, 3, ch, cw), np.float32)
        heat = np.zeros((size, len(CLASS_NAMES), ch // STRIDE, cw // STRIDE), np.float32)
        weight = np.ones((size, 1, ch // STRIDE, cw // STRIDE), np.float32)
        reg = []
        for b, i in enumerate(rng.integers(0, len(self.cache.images), size)):
            img, boxes, cls, positive = self.crop(int(i), rng)
            images[b] = img[..., ::-1].transpose(2, 0, 1) / 255.0
            reg.append(targets(boxes, cls, positive, heat[b], weight[b, 0], b))
        cat = lambda k: np.concatenate([r[k] for r in reg])  # noqa: E731
        return {"images": images, "heat": heat, "weight": weight,
                "reg": {"b": cat("b"), "y": cat("y"), "x": cat("x"), "ltrb": cat("ltrb"), "w": cat("w")}}


def targets(boxes, cls, positive, heat, weight, b: int) -> dict:
    """Fill ``heat`` (nc, h, w) and ``weight`` (h, w) in place for one crop; regression cells out.

    heat_c(cell) = max over boxes of class c of exp(-dx^2 / 2 sx^2 - dy^2 / 2 sy^2) (cells), 1 at
    the centre's cell; weight 0 over ignored boxes. Regression cells: heat >= REG_MIN_HEAT with the
    cell centre inside the box, each owned by the box of the highest heat there; targets ltrb (px).
    """
    nc, h, w = heat.shape
    owner_g = np.zeros((h, w), np.float32)
    owner_ltrb = np.zeros((h, w, 4), np.float32)
    for x0, y0, x1, y1 in boxes[~positive]:
        weight[int(y0 // STRIDE):int(np.ceil(y1 / STRIDE)), int(x0 // STRIDE):int(np.ceil(x1 / STRIDE))] = 0.0
    for (x0, y0, x1, y1), c in zip(boxes[positive], cls[positive]):
        cx, cy = (x0 + x1) / 2 / STRIDE, (y0 + y1) / 2 / STRIDE  # centre in cells
        sx = max(SIGMA_MIN_CELLS, SIGMA_FRACTION * (x1 - x0) / STRIDE)
        sy = max(SIGMA_MIN_CELLS, SIGMA_FRACTION * (y1 - y0) / STRIDE)
        gx0, gx1 = max(0, int(cx - 3 * sx)), min(w, int(cx + 3 * sx) + 1)
        gy0, gy1 = max(0, int(cy - 3 * sy)), min(h, int(cy + 3 * sy) + 1)
        px, py = (np.arange(gx0, gx1) + 0.5), (np.arange(gy0, gy1) + 0.5)  # cell centres (cells)
        g = np.exp(-((px[None] - cx) ** 2) / (2 * sx * sx) - ((py[:, None] - cy) ** 2) / (2 * sy * sy))
        pi, pj = min(h - 1, int(cy)) - gy0, min(w - 1, int(cx)) - gx0
        g[pi, pj] = 1.0
        k = int(c) - 1
        np.maximum(heat[k, gy0:gy1, gx0:gx1], g, out=heat[k, gy0:gy1, gx0:gx1])
        cxp, cyp = px * STRIDE, py * STRIDE  # cell centres (px)
        ltrb = np.stack(np.broadcast_arrays(cxp[None] - x0, cyp[:, None] - y0, x1 - cxp[None], y1 - cyp[:, None]), -1)
        inside = np.all(ltrb > 0, axis=-1)
        take = ((g >= REG_MIN_HEAT) & inside) | (g >= 1.0)
        take &= g > owner_g[gy0:gy1, gx0:gx1]
        owner_g[gy0:gy1, gx0:gx1][take] = g[take]
        owner_ltrb[gy0:gy1, gx0:gx1][take] = np.maximum(ltrb[take], 0.25)
    ys, xs = np.nonzero(owner_g)
    return {"b": np.full(len(ys), b, np.int64), "y": ys, "x": xs, "ltrb": owner_ltrb[ys, xs], "w": owner_g[ys, xs]}

