"""The human lines of a report (``v2i.offline.spec.summary`` for eval and demo, the report PNGs'
titles): a target that was not detected reads "not seen", not "first seen at never"."""

from __future__ import annotations

import copy

from v2i.reports.report_plots import title_lines
from v2i.offline.spec import summary

SEEN = {"first_detection_distance_m": 79.46, "mean_bev_iou": 0.754, "rmse_m": 0.503, "detected_cycles": 134,
        "track_ids": 1, "id_switches": 0}
UNSEEN = {"first_detection_distance_m": None, "mean_bev_iou": None, "rmse_m": None, "detected_cycles": 0,
          "track_ids": 0, "id_switches": 0}


def _report(target: dict, vehicle_only: dict) -> dict:
    vehicle = {"target": target, "vehicle_only": vehicle_only, "output_deadline_miss_ratio": 0.0}
    return {"scenario": "red-light-runner", "profile": "lte-v2x", "fusion": "kf", "compensation": "predict",
            "fusion_mode": "adaptive", "seed": 0, "duration_s": 20.0, "cycles": 200, "driver": "eval",
            "target": target, "vehicle_only": vehicle_only, "mode_share": {"intra": 0.5, "vehicle_only": 0.5},
            "output_deadline_miss_ratio": 0.0, "rsu_deadline_miss_ratio": 0.01, "rsu_messages_received": 99,
            "clock_offset_error_ms": {"p50": 1.0, "p95": 1.1, "max": 1.2}, "clock_offset_error_naive_ms": {"p95": 19.4},
            "clock_drift_error_ppm": 3.0, "rsu_perception": {"frames": 0}, "displacement_error_m": None,
            "vehicles": {"ego": copy.deepcopy(vehicle), "car-2": copy.deepcopy(vehicle)}}


def test_a_target_never_detected_reads_not_seen():
    text = summary(_report(UNSEEN, UNSEEN))
    assert "never" not in text
    assert "target (red-light-runner): not seen with V2I, not seen vehicle-only\n" in text
    assert "  target: not detected in any cycle (no IoU or RMSE)\n" in text
    assert "vehicle car-2: target not seen (vehicle-only: not seen), RMSE n/a," in text
    title = title_lines(_report(UNSEEN, UNSEEN), None)
    assert "never" not in title and "target not seen (vehicle only: not seen), RMSE n/a" in title


def test_a_detected_target_reads_its_distance_and_accuracy():
    text = summary(_report(SEEN, {**UNSEEN, "first_detection_distance_m": 31.2}))
    assert "target (red-light-runner): first seen at 79.5 m with V2I, first seen at 31.2 m vehicle-only (2.5x farther)" \
        in text
    assert "  target: mean BEV IoU 0.754, RMSE 0.50 m over 134 cycles\n" in text
    assert "vehicle ego: target first seen at 79.5 m (vehicle-only: first seen at 31.2 m), RMSE 0.50 m," in text
    assert "target first seen at 79.5 m (vehicle only: first seen at 31.2 m), RMSE 0.50 m" in title_lines(
        _report(SEEN, {**UNSEEN, "first_detection_distance_m": 31.2}), None)


def test_crowded_out_cycles_and_lists_lost_before_fusion_are_said_only_when_there_are_any():
    quiet = summary({**_report(SEEN, SEEN), "crowded_out_cycles": 0, "rsu_lists_accepted": {"rsu1": {"accepted": 99, "sent": 99}}})
    assert "crowded out" not in quiet and "RSU lists received 99\n" in quiet
    flooded = summary({**_report(SEEN, SEEN), "crowded_out_cycles": 67,
                       "rsu_lists_accepted": {"rsu1": {"accepted": 44, "sent": 101}, "cpm": {"accepted": 5, "sent": None}}})
    assert "RSU 1.0%, 67 cycles crowded out; modes:" in flooded
    assert "RSU lists received 99, accepted 44 of 101 sent\n" in flooded  # an RSU that numbers none is left out
