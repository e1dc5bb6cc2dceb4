"""How well the RSU perceives (``rsu_perception`` in the report): its raw per-frame
detections in ``map`` against the ground truth it could see, frame by frame.

Per frame, detections and the visible ground truth are matched one-to-one by centre
distance (Hungarian: ``v2i.fusion.lsap``) within ``MATCH_GATE_M``. Then

    recall    = matched truths / visible truths       (per range bin and overall)
    precision = matched detections / detections
    mean_error_m[bin] = mean |p_det - p_true| over the matches whose truth is in the bin

with range the horizontal distance from the camera. Saravanan et al. Sec. I reports CAROM's mean
error as 0.8 m within 50 m and 1.7 m from 50 to 120 m: ``ERROR_BINS_M`` are those bins.
Only counts and sums are kept, so a tally merges (``merge``) and travels in RSU metrics.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from v2i.fusion.association import center_distance_cost
from v2i.fusion.lsap import linear_sum_assignment

MATCH_GATE_M = 5.0  # a detection farther than this from every visible truth is a false positive
ERROR_BINS_M = ((0.0, 50.0), (50.0, 120.0))
RECALL_BINS_M = ((0.0, 50.0), (50.0, 80.0), (80.0, 120.0))
MAX_TIMING_SAMPLES = 100_000  # detector times kept for p50/p99 (a 5 h run at 5 Hz)


def _label(lo: float, hi: float) -> str:
    return f"{lo:g}-{hi:g}m"


def _bin_index(range_m: np.ndarray, bins) -> np.ndarray:
    """(N,) index of the bin holding each range; -1 outside every bin."""
    out = np.full(len(range_m), -1, dtype=np.int64)
    for i, (lo, hi) in enumerate(bins):
        out[(range_m >= lo) & (range_m < hi)] = i
    return out


def match(truth_xy: np.ndarray, det_xy: np.ndarray, gate_m: float = MATCH_GATE_M) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matches (truth index (M,), detection index (M,)) minimising the summed
    centre distance, each pair within ``gate_m``. truth_xy (T, 2), det_xy (D, 2) m."""
    if not len(truth_xy) or not len(det_xy):
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    d = center_distance_cost(truth_xy, det_xy)
    rows, cols = linear_sum_assignment(np.where(d <= gate_m, d, 1e6))
    ok = d[rows, cols] <= gate_m
    return rows[ok], cols[ok]


@dataclass
class PerceptionTally:
    """Counts and sums over frames; ``scores()`` is the report section."""

    frames: int = 0
    truths: np.ndarray = field(default_factory=lambda: np.zeros(len(RECALL_BINS_M), dtype=np.int64))
    found: np.ndarray = field(default_factory=lambda: np.zeros(len(RECALL_BINS_M), dtype=np.int64))
    detections: int = 0
    true_detections: int = 0
    error_sum_m: np.ndarray = field(default_factory=lambda: np.zeros(len(ERROR_BINS_M)))
    error_count: np.ndarray = field(default_factory=lambda: np.zeros(len(ERROR_BINS_M), dtype=np.int64))
    detector_ms: list[float] = field(default_factory=list)
    calibration_reprojection_px: float | None = None
    camera_xy: np.ndarray = field(default_factory=lambda: np.zeros(2))  # (2,) m, for add_frame

    @classmethod
    def of_source(cls, source, camera_xy) -> "PerceptionTally":
        """An empty tally for an RSU source (``rsu_service.source``) whose camera is at
        ``camera_xy`` (2,) m; an image source's calibration error is noted."""
        perception = getattr(source, "perception", None)
        return cls(calibration_reprojection_px=None if perception is None else perception.calibration.reprojection_px,
                   camera_xy=np.asarray(camera_xy, dtype=float))

    def add_frame(self, frame) -> None:
        """One ``rsu_service.source.Frame``; a frame without its visible truth (a recording) is not scored."""
        if frame.visible_truth_xy is not None:
            self.add(frame.visible_truth_xy, frame.detections.xy, self.camera_xy, frame.detector_ms)

    def add(self, truth_xy: np.ndarray, det_xy: np.ndarray, camera_xy: np.ndarray,
            detector_ms: float | None = None) -> None:
        """One frame: visible ground truth (T, 2) and detections (D, 2) in map (m), camera (2,)."""
        truth_xy, det_xy = np.asarray(truth_xy, float).reshape(-1, 2), np.asarray(det_xy, float).reshape(-1, 2)
        ti, di = match(truth_xy, det_xy)
        truth_range = np.hypot(*(truth_xy - camera_xy).T) if len(truth_xy) else np.zeros(0)
        rb = _bin_index(truth_range, RECALL_BINS_M)
        np.add.at(self.truths, rb[rb >= 0], 1)
        np.add.at(self.found, rb[ti][rb[ti] >= 0], 1)
        eb = _bin_index(truth_range[ti], ERROR_BINS_M)
        err = np.hypot(*(truth_xy[ti] - det_xy[di]).T) if len(ti) else np.zeros(0)
        np.add.at(self.error_sum_m, eb[eb >= 0], err[eb >= 0])
        np.add.at(self.error_count, eb[eb >= 0], 1)
        self.frames += 1
        self.detections += len(det_xy)
        self.true_detections += len(ti)
        if detector_ms is not None and len(self.detector_ms) < MAX_TIMING_SAMPLES:
            self.detector_ms.append(float(detector_ms))

    def scores(self) -> dict:
        def ratio(a, b):
            return round(float(a) / float(b), 4) if b else None

        ms = np.asarray(self.detector_ms)
        return {
            "frames": self.frames,
            "recall": ratio(self.found.sum(), self.truths.sum()),
            "precision": ratio(self.true_detections, self.detections),
            "recall_by_range": {_label(*b): ratio(f, t) for b, f, t in zip(RECALL_BINS_M, self.found, self.truths)},
            "visible_truths_by_range": {_label(*b): int(t) for b, t in zip(RECALL_BINS_M, self.truths)},
            "mean_error_m": {_label(*b): ratio(s, n) for b, s, n in zip(ERROR_BINS_M, self.error_sum_m, self.error_count)},
            "detector_ms": ({"p50": round(float(np.percentile(ms, 50)), 2), "p99": round(float(np.percentile(ms, 99)), 2)}
                            if len(ms) else None),
            "calibration_reprojection_px": self.calibration_reprojection_px,
        }
