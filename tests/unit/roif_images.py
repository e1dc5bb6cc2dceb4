"""Synthetic image pairs for the ROIF tests: a textured OBU image and its RSU view by a known homography."""

from __future__ import annotations

import cv2
import numpy as np

W, H = 640, 384
H_TRUE = np.array([[0.9, 0.05, 20.0], [-0.03, 0.95, 10.0], [1e-4, -5e-5, 1.0]])  # OBU px -> RSU px
OBU_BOXES = np.array([[50, 50, 200, 160], [300, 100, 450, 250], [420, 200, 600, 360]], float)


def textured(seed: int) -> np.ndarray:
    """A 640 x 384 BGR image with blocky noise and discs: plenty of ORB corners."""
    rng = np.random.default_rng(seed)
    img = cv2.resize((rng.random((H // 8, W // 8, 3)) * 255).astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST)
    for _ in range(60):
        colour = tuple(int(v) for v in rng.integers(0, 255, 3))
        cv2.circle(img, (int(rng.integers(0, W)), int(rng.integers(0, H))), int(rng.integers(3, 30)), colour, -1)
    return cv2.GaussianBlur(img, (3, 3), 0)
