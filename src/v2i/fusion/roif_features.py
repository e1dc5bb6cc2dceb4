"""What one camera contributes to ROIF (the thesis's Sec. 5.3): its boxes and the ORB features inside them.

ROIF splits at the wire: the RSU computes its ``ViewFeatures`` next to its detector and sends
them (``schemas.image_messages.RsuImageFeatures``); the OBU computes its own from its camera
and fuses the two (``v2i.fusion.roif.roif_fuse``). Neither side needs the other's image.

Pure: arrays in, arrays out; no clock, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

DESCRIPTOR_BYTES = 32  # ORB: 256-bit binary descriptors


@dataclass(frozen=True)
class ViewFeatures:
    """One camera frame as ROIF sees it.

    boxes (N, 4) float [x1, y1, x2, y2] px, scores (N,) float, cls (N,) int64 (ObjectClass codes),
    keypoints (K, 2) float px (ORB ``pt``: u, v), descriptors (K, 32) uint8,
    box_index (K,) int64: the box each keypoint was found in (first box containing it, boxes
    rounded outward as the detection mask is), image_wh (width, height) px.
    """

    boxes: np.ndarray
    scores: np.ndarray
    cls: np.ndarray
    keypoints: np.ndarray
    descriptors: np.ndarray
    box_index: np.ndarray
    image_wh: tuple[int, int]

    @classmethod
    def of(cls, boxes, scores, classes, keypoints, descriptors, image_wh: tuple[int, int],
           box_index=None) -> ViewFeatures:
        """Arrays normalised to the documented shapes and dtypes; ``box_index`` computed when None."""
        xyxy = np.asarray(boxes, float).reshape(-1, 4)
        kp = np.asarray(keypoints, float).reshape(-1, 2)
        index = keypoint_box_index(kp, xyxy) if box_index is None else np.asarray(box_index, np.int64).reshape(-1)
        return cls(xyxy, np.asarray(scores, float).reshape(-1), np.asarray(classes, np.int64).reshape(-1), kp,
                   np.asarray(descriptors, np.uint8).reshape(-1, DESCRIPTOR_BYTES), index,
                   (int(image_wh[0]), int(image_wh[1])))

    @classmethod
    def of_message(cls, msg) -> ViewFeatures:
        """The frame of an RSU's ``schemas.image_messages.RsuImageFeatures`` (float64 px, uint8 descriptors)."""
        from schemas import image_messages as wire

        k = msg.n_keypoints
        return cls.of(*msg.boxes.arrays(), wire.column(msg.keypoints, wire.F4, k, 2, "keypoints").astype(float),
                      wire.column(msg.descriptors, wire.U1, k, wire.DESCRIPTOR_BYTES, "descriptors"),
                      (msg.image_width, msg.image_height),
                      wire.column(msg.keypoint_box, wire.U2, k, 1, "keypoint_box").ravel())

    @property
    def detections(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(xyxy (N, 4), scores (N,), cls (N,))."""
        return self.boxes, self.scores, self.cls


def rounded_out(xyxy: np.ndarray, image_wh: tuple[int, int]) -> np.ndarray:
    """Integer pixel ranges (N, 4) [c1, r1, c2, r2) of boxes (N, 4) rounded outward and clipped."""
    b = np.asarray(xyxy, float).reshape(-1, 4)
    w, h = image_wh
    lo = np.maximum(np.floor(b[:, :2]), 0)
    hi = np.minimum(np.ceil(b[:, 2:]), [w, h])
    return np.column_stack([lo, hi]).astype(np.int64)


def box_mask(shape_hw: tuple[int, int], xyxy: np.ndarray) -> np.ndarray:
    """uint8 mask (H, W): 255 inside any of the boxes (N, 4) px (rounded outward, clipped), else 0."""
    h, w = shape_hw
    mask = np.zeros((h, w), dtype=np.uint8)
    for c1, r1, c2, r2 in rounded_out(xyxy, (w, h)):
        if c2 > c1 and r2 > r1:
            mask[r1:r2, c1:c2] = 255
    return mask


def keypoint_box_index(keypoints: np.ndarray, xyxy: np.ndarray) -> np.ndarray:
    """(K,) int64: for each keypoint (K, 2) px the first box (N, 4) whose outward-rounded pixel
    range holds it (the mask ORB ran under), else the box with the nearest centre; -1 without boxes."""
    kp = np.asarray(keypoints, float).reshape(-1, 2)
    b = np.asarray(xyxy, float).reshape(-1, 4)
    if not len(b):
        return np.full(len(kp), -1, np.int64)
    lo, hi = np.floor(b[:, :2]), np.ceil(b[:, 2:])
    inside = np.all((kp[:, None, :] >= lo[None]) & (kp[:, None, :] <= hi[None]), axis=2)  # (K, N)
    centre = (b[:, :2] + b[:, 2:]) / 2.0
    nearest = np.argmin(np.linalg.norm(kp[:, None, :] - centre[None], axis=2), axis=1)
    return np.where(inside.any(axis=1), np.argmax(inside, axis=1), nearest).astype(np.int64)


def orb_features(image: np.ndarray, xyxy: np.ndarray, max_features: int, fast_threshold: int, patch_px: int,
                 levels: int) -> tuple[np.ndarray, np.ndarray]:
    """ORB keypoints (K, 2) px and descriptors (K, 32) uint8 inside the boxes (N, 4) of an image
    (H, W[, 3] BGR), K <= ``max_features`` (the strongest corners, by ORB's Harris score)."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    orb = cv2.ORB_create(nfeatures=max_features, nlevels=levels, edgeThreshold=patch_px, patchSize=patch_px,
                         fastThreshold=fast_threshold)
    keypoints, descriptors = orb.detectAndCompute(grey, box_mask(grey.shape[:2], xyxy))
    if descriptors is None or not keypoints:
        return np.zeros((0, 2)), np.zeros((0, DESCRIPTOR_BYTES), dtype=np.uint8)
    return np.array([kp.pt for kp in keypoints], dtype=float), descriptors


def view_features(image: np.ndarray, detections: tuple, config, max_features: int | None = None) -> ViewFeatures:
    """The ``ViewFeatures`` of an image (H, W, 3) BGR and its detections (xyxy (N, 4), scores (N,),
    cls (N,)); ORB as ``config`` (a ``v2i.fusion.roif.RoifConfig``) says, at most ``max_features``
    keypoints (default ``config.orb_features``)."""
    xyxy, scores, cls = detections
    xyxy = np.asarray(xyxy, float).reshape(-1, 4)
    cap = config.orb_features if max_features is None else int(max_features)
    kp, desc = orb_features(image, xyxy, cap, config.orb_fast_threshold, config.orb_patch_px, config.orb_levels)
    return ViewFeatures.of(xyxy, scores, cls, kp, desc, (image.shape[1], image.shape[0]))
