"""Image perception of the RSU: detector boxes through the calibrated ground homography.

An image (H, W, 3) BGR goes through the ONNX detector (``v2i.perception.detector``); each box's
ground contact goes through the calibration's inverse homography into ``map``, with its
covariance propagated from the pixel error (``v2i.perception.ground``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from v2i.core.objects import ObjectArray


class ImagePerception:
    """Detector + calibration: an image in, objects in map out (ids -1, no velocity)."""

    def __init__(self, detector, calibration, camera_xy=None, pixel_sigma_px: float = 1.0,
                 max_range_m: float | None = None):
        """``max_range_m``: objects farther from ``camera_xy`` are dropped (the camera's working
        range: beyond it a pixel spans metres, Saravanan et al. Sec. V-B)."""
        self.detector = detector
        self.calibration = calibration
        self.camera_xy = None if camera_xy is None else np.asarray(camera_xy, dtype=float)
        self.pixel_sigma_px = pixel_sigma_px
        self.max_range_m = max_range_m

    @classmethod
    def open(cls, calibration_path: str | Path, model_path: str | Path | None, score_threshold: float,
             camera_xy=None, threads: int | None = None, max_range_m: float | None = None) -> "ImagePerception":
        """The shipped model (or ``model_path``) and the calibration file at ``calibration_path``."""
        from v2i.perception.calibration import load_calibration
        from v2i.perception.detector import OnnxDetector

        calibration = load_calibration(calibration_path)
        if camera_xy is None and calibration.camera_xy is None:
            raise ValueError(f"{calibration_path}: a homography-only calibration does not tell where the camera "
                             "stands; calibrate with intrinsics (v2i camera calibrate --fov-deg or --intrinsics)")
        detector = OnnxDetector(model_path, threads=threads, score_threshold=score_threshold)
        detector.detect(np.zeros((calibration.height, calibration.width, 3), np.uint8))  # warm-up: the first run is slow
        return cls(detector, calibration, camera_xy, max_range_m=max_range_m)

    def perceive(self, image: np.ndarray) -> tuple[ObjectArray, float]:
        """Objects in map and the detector's time on this image (ms)."""
        from v2i.perception.ground import pixels_to_map

        boxes = self.detector.detect(image)
        self.last_detections = (np.asarray(boxes.xyxy, float).reshape(-1, 4), np.asarray(boxes.scores, float),
                                np.asarray(boxes.cls, np.int64))  # the boxes ROIF's features are found in
        objects = pixels_to_map(self.calibration, boxes.xyxy, boxes.cls, boxes.scores,
                                pixel_sigma_px=self.pixel_sigma_px, camera_xy=self.camera_xy)
        if self.max_range_m is not None and self.camera_xy is not None and len(objects):
            objects = objects.take(np.hypot(*(objects.xy - self.camera_xy).T) <= self.max_range_m)
        return objects, self.detector.last_ms

    def features(self, image: np.ndarray, max_features: int):
        """ROIF features (``v2i.fusion.roif_features.ViewFeatures``) of the image ``perceive`` last saw:
        its detector boxes and at most ``max_features`` ORB keypoints + descriptors inside them."""
        from v2i.fusion.roif import RoifConfig
        from v2i.fusion.roif_features import view_features

        return view_features(image, self.last_detections, RoifConfig(), max_features)
