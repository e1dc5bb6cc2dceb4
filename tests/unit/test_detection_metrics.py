"""Centre-distance mAP (nuScenes convention), MOT metrics and NEES on hand-computed cases; the
streaming versions (``CenterDistanceAp``, ``MotTally``) equal the batch reference and motmetrics."""

import math

import numpy as np
import pytest

from v2i.scoring.detection_metrics import (
    CenterDistanceAp, MotTally, _confidence_order, _frame_flags, _greedy_match, _greedy_matches, average_precision,
    bin_label, center_distance_ap, frame_flags_reference, mot_metrics, nees, nees_values,
)
from v2i.fusion.association import center_distance_cost
from v2i.core.objects import ObjectArray


def objs(xy, confidence=None) -> ObjectArray:
    """Cars at centres xy (N, 2) m in base_link with the given confidences."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    n = len(xy)
    return ObjectArray(
        ids=np.arange(n, dtype=np.int64), cls=np.ones(n, dtype=np.int64), xy=xy, z=np.zeros(n),
        lwh=np.tile([4.6, 1.85, 1.5], (n, 1)), yaw=np.zeros(n), vxy=np.zeros((n, 2)),
        confidence=None if confidence is None else np.asarray(confidence, dtype=float),
    )


THRESHOLDS = ("AP@0.5", "AP@1", "AP@2", "AP@4")


# --- centre-distance AP -------------------------------------------------------------------

def test_perfect_predictions_score_one_in_every_bin():
    truth = objs([[10.0, 0.0], [-25.0, 5.0], [50.0, 3.0], [0.0, 70.0]])
    frames = [(truth, objs(truth.xy, [0.9, 0.8, 0.7, 0.6])) for _ in range(3)]
    result = center_distance_ap(frames)
    assert set(result) == {"0-40m", "40-80m", "overall"}
    for label in result:
        assert result[label]["mAP"] == pytest.approx(1.0)
        assert all(result[label][k] == pytest.approx(1.0) for k in THRESHOLDS)
    assert result["overall"]["num_truth"] == 12 and result["0-40m"]["num_truth"] == 6


def test_predictions_all_far_score_zero():
    truth = objs([[10.0, 0.0], [20.0, 0.0]])
    frames = [(truth, objs(truth.xy + [0.0, 5.0], [0.9, 0.8]))]
    assert center_distance_ap(frames)["overall"]["mAP"] == 0.0


def test_half_of_the_truth_found_with_full_precision():
    # recall 0.5 at precision 1: p(r) = 1 for r <= 0.5 and 0 beyond; AP = mean over
    # r = 0.11..1.00 of max(p - 0.1, 0) / 0.9 = 40 * 0.9 / 90 / 0.9 = 4/9
    truth = objs([[10.0, 0.0], [20.0, 0.0]])
    result = center_distance_ap([(truth, objs([[10.0, 0.0]], [0.9]))])
    assert result["overall"]["mAP"] == pytest.approx(4.0 / 9.0)


def test_offset_between_thresholds_counts_only_at_the_wider_ones():
    truth = objs([[10.0, 0.0]])
    result = center_distance_ap([(truth, objs([[10.75, 0.0]], [0.9]))])["overall"]
    assert result["AP@0.5"] == 0.0
    assert result["AP@1"] == result["AP@2"] == result["AP@4"] == pytest.approx(1.0)
    assert result["mAP"] == pytest.approx(0.75)


def test_match_is_strictly_inside_the_threshold():
    truth = objs([[10.0, 0.0]])
    assert center_distance_ap([(truth, objs([[11.0, 0.0]], [0.9]))])["overall"]["AP@1"] == 0.0


def test_confident_false_positive_ranked_first():
    # ranked: FP, TP, TP over 2 truths -> (r, p) = (0, 0), (0.5, 0.5), (1, 2/3), interpolated
    # linearly. r = 0.11..0.50: p - 0.1 = (i - 10) / 100, sum 8.2; r = 0.51..1.00:
    # p - 0.1 = 0.4 + j / 300, j = 1..50, sum 24.25; AP = (8.2 + 24.25) / 90 / 0.9
    truth = objs([[10.0, 0.0], [20.0, 0.0]])
    preds = objs([[50.0, 50.0], [10.0, 0.0], [20.0, 0.0]], [0.9, 0.8, 0.7])
    assert center_distance_ap([(truth, preds)])["overall"]["mAP"] == pytest.approx(32.45 / 81.0)


def test_each_truth_is_matched_once_in_confidence_order():
    dist = np.array([[0.0], [0.0]])
    assert _greedy_match(dist, np.array([1, 0]), 1.0).tolist() == [False, True]
    # the most confident prediction takes its nearest truth, the next one the remaining one
    dist = np.array([[0.3, 0.5], [0.2, 0.9]])
    assert _greedy_match(dist, np.array([0, 1]), 1.0).tolist() == [True, True]
    assert _greedy_match(dist, np.array([0, 1]), 0.6).tolist() == [True, False]


def test_ranking_spans_frames():
    # the same objects split over two frames give the same AP as in one frame
    truth = objs([[10.0, 0.0], [20.0, 0.0]])
    preds = objs([[50.0, 50.0], [10.0, 0.0], [20.0, 0.0]], [0.9, 0.8, 0.7])
    one = center_distance_ap([(truth, preds)])["overall"]["mAP"]
    split = center_distance_ap([(truth.take([0]), preds.take([0, 1])), (truth.take([1]), preds.take([2]))])
    assert split["overall"]["mAP"] == pytest.approx(one)


def test_range_bins_filter_truth_and_predictions_by_their_own_distance():
    truth = objs([[30.0, 0.0], [0.0, -60.0]])
    result = center_distance_ap([(truth, objs([[0.0, -60.0]], [0.9]))])
    assert result["0-40m"]["mAP"] == 0.0 and result["0-40m"]["num_predictions"] == 0
    assert result["40-80m"]["mAP"] == pytest.approx(1.0)
    assert result["overall"]["mAP"] == pytest.approx(4.0 / 9.0)
    empty = center_distance_ap([(truth, objs([[0.0, -60.0]], [0.9]))], range_bins_m=[(100.0, 200.0)])
    assert empty == {"100-200m": {"num_truth": 0, "num_predictions": 0, "AP@0.5": None, "AP@1": None,
                                  "AP@2": None, "AP@4": None, "mAP": None}}


def test_bin_labels_and_degenerate_inputs():
    assert bin_label(0.0, math.inf) == "overall" and bin_label(40.0, 80.0) == "40-80m"
    assert center_distance_ap([])["overall"]["mAP"] is None
    assert average_precision(np.zeros(0), np.zeros(0, dtype=bool), 3) == 0.0
    no_preds = center_distance_ap([(objs([[5.0, 0.0]]), ObjectArray.empty())])
    assert no_preds["overall"]["mAP"] == 0.0


def streaming_ap(frames, **kw) -> dict:
    ap = CenterDistanceAp(**kw)
    for truth, pred in frames:
        ap.add_frame(truth.xy, pred.xy, pred.confidence)
    return ap.result()


def generated_frames(rng: np.random.Generator, n_frames: int) -> list:
    """Frames of 0-12 truths over +-90 m (across every bin edge), 80 % detected with 0.3-3 m
    errors, 0-3 false positives; confidences on a 0.1 grid, so ties within and across frames;
    a fifth of the detections doubled with the same confidence (tied rivals for one truth)."""
    frames = []
    for _ in range(n_frames):
        truth = rng.uniform(-90.0, 90.0, (rng.integers(0, 13), 2))
        found = truth[rng.random(len(truth)) < 0.8]
        pred = np.vstack([found + rng.normal(0.0, rng.choice([0.3, 1.0, 3.0]), found.shape),
                          rng.uniform(-90.0, 90.0, (rng.integers(0, 4), 2))])
        confidence = np.round(rng.random(len(pred)), 1)
        twin = rng.random(len(pred)) < 0.2
        pred = np.vstack([pred, pred[twin] + rng.normal(0.0, 0.5, (twin.sum(), 2))])
        frames.append((objs(truth), objs(pred, np.concatenate([confidence, confidence[twin]]))))
    return frames


def test_streaming_ap_equals_the_batch_reference_on_generated_frames():
    rng = np.random.default_rng(7)
    for _ in range(25):
        frames = generated_frames(rng, int(rng.integers(1, 60)))
        batch, streamed = center_distance_ap(frames), streaming_ap(frames)
        assert batch.keys() == streamed.keys()
        for label, ref in batch.items():
            assert streamed[label].keys() == ref.keys()
            for key, value in ref.items():
                got = streamed[label][key]
                assert (value is None and got is None) or got == pytest.approx(value, abs=1e-9)
    assert 0.0 < batch["overall"]["mAP"] < 1.0  # not a degenerate case


def test_streaming_ap_hand_computed_cases():
    truth = objs([[10.0, 0.0], [20.0, 0.0]])
    preds = objs([[50.0, 50.0], [10.0, 0.0], [20.0, 0.0]], [0.9, 0.8, 0.7])
    split = [(truth.take([0]), preds.take([0, 1])), (truth.take([1]), preds.take([2]))]
    assert streaming_ap(split)["overall"]["mAP"] == pytest.approx(32.45 / 81.0)
    assert streaming_ap([(objs([[10.0, 0.0]]), objs([[10.75, 0.0]], [0.9]))])["overall"]["mAP"] == pytest.approx(0.75)
    assert streaming_ap([], range_bins_m=[(100.0, 200.0)]) == center_distance_ap([], range_bins_m=[(100.0, 200.0)])


# --- MOT metrics --------------------------------------------------------------------------

def _mot_frames():
    a, b = [0.0, 0.0], [10.0, 0.0]
    return [
        ([1, 2], [a, b], [10, 20], [[0.1, 0.0], [10.0, 0.1]]),  # both tracked
        ([1, 2], [a, b], [10, 30], [[0.1, 0.0], [10.0, 0.1]]),  # truth 2 switches 20 -> 30
        ([1, 2], [a, b], [10], [[0.1, 0.0]]),  # truth 2 missed
        ([1], [a], [10, 40], [[0.1, 0.0], [50.0, 50.0]]),  # 40 is a false positive
    ]


def test_mot_metrics_hand_computed():
    r = mot_metrics(_mot_frames(), max_distance_m=2.0)
    # 7 truth objects, 1 miss + 1 FP + 1 switch: MOTA = 1 - 3/7
    assert r["mota"] == pytest.approx(4.0 / 7.0)
    # identity matching 1<->10 (4 frames), 2<->20 or 30 (1 frame): IDTP 5 over 7 + 7 detections
    assert r["idf1"] == pytest.approx(10.0 / 14.0)
    assert (r["id_switches"], r["num_frames"], r["misses"], r["false_positives"], r["num_truth"]) == (1, 4, 1, 1, 7)
    assert r["motp_m"] == pytest.approx(0.1)


def test_mot_gate_and_empty_frames():
    far = [([1], [[0.0, 0.0]], [5], [[2.5, 0.0]])]
    r = mot_metrics(far + [([], np.zeros((0, 2)), [], np.zeros((0, 2)))], max_distance_m=2.0)
    assert (r["misses"], r["false_positives"], r["num_frames"]) == (1, 1, 2)
    assert r["mota"] == pytest.approx(-1.0) and r["motp_m"] is None
    assert mot_metrics(far, max_distance_m=3.0)["mota"] == pytest.approx(1.0)


def generated_tracks(rng: np.random.Generator, n_frames: int) -> list:
    """Frames of 1-9 moving truths on a 0.5 m grid (ties in distance), each present 90 % and
    tracked 85 % of the frames with 0.3-1.5 m errors; new track ids, swapped ids and false
    positives now and then."""
    n = int(rng.integers(1, 10))
    pos, vel = rng.uniform(0.0, 20.0, (n, 2)), rng.normal(0.0, 1.0, (n, 2))
    track, next_id, frames = np.arange(n) + 100, 200, []
    for f in range(n_frames):
        pos = pos + 0.1 * vel
        present = rng.random(n) < 0.9
        seen = present & (rng.random(n) < 0.85)
        if rng.random() < 0.05:
            track[rng.integers(n)], next_id = next_id, next_id + 1
        if rng.random() < 0.05 and n > 1:
            i, j = rng.choice(n, 2, replace=False)
            track[[i, j]] = track[[j, i]]
        hyp_xy = np.round(2.0 * (pos[seen] + rng.normal(0.0, rng.choice([0.3, 1.5]), (seen.sum(), 2)))) / 2.0
        n_fp = int(rng.integers(0, 3))
        hyp_xy = np.vstack([hyp_xy, rng.uniform(0.0, 20.0, (n_fp, 2))])
        hyp_ids = np.concatenate([track[seen], 900 + 3 * f + np.arange(n_fp)])
        frames.append((np.arange(n)[present], np.round(2.0 * pos[present]) / 2.0, hyp_ids, hyp_xy))
    return frames


def test_streaming_mot_equals_motmetrics_on_generated_tracks():
    rng = np.random.default_rng(11)
    switches = 0
    for _ in range(25):
        frames = generated_tracks(rng, int(rng.integers(1, 80)))
        ref, tally = mot_metrics(frames), MotTally()
        for frame in frames:
            tally.add_frame(*frame)
        got = tally.result()
        assert got.keys() == ref.keys()
        for key in ("mota", "idf1", "id_switches", "num_frames", "misses", "false_positives", "num_truth"):
            assert got[key] == ref[key], (key, got, ref)
        assert got["motp_m"] == pytest.approx(ref["motp_m"], abs=1e-9)
        switches += got["id_switches"]
    assert switches > 10  # the cases exercise identity switches


def test_streaming_mot_hand_computed():
    tally = MotTally(max_distance_m=2.0)
    for frame in _mot_frames():
        tally.add_frame(*frame)
    r = tally.result()
    assert r["mota"] == pytest.approx(4.0 / 7.0) and r["idf1"] == pytest.approx(10.0 / 14.0)
    assert (r["id_switches"], r["misses"], r["false_positives"], r["num_truth"]) == (1, 1, 1, 7)
    empty = MotTally().result()
    assert empty["mota"] is None and empty["idf1"] is None and empty["num_frames"] == 0


# --- NEES ---------------------------------------------------------------------------------

def test_nees_exact_values():
    r = nees(np.array([[1.0, 0.0], [2.0, 0.0]]), np.array([np.eye(2), np.diag([4.0, 1.0])]))
    assert r["mean"] == pytest.approx(1.0) and r["fraction_inside"] == 1.0 and r["samples"] == 2
    lo, hi = r["interval"]
    assert lo == pytest.approx(0.0506356, rel=1e-5) and hi == pytest.approx(7.377759, rel=1e-5)
    assert nees(np.zeros((0, 2)), np.zeros((0, 2, 2)))["mean"] is None


def test_nees_values_one_at_a_time_equal_the_batch_bit_for_bit():
    rng = np.random.default_rng(5)
    a = rng.normal(size=(2000, 2, 2))
    cov = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(2)
    errors = rng.normal(size=(2000, 2)) * rng.uniform(0.01, 100.0, (2000, 1))
    one_by_one = np.array([nees_values(errors[k:k + 1], cov[k:k + 1])[0] for k in range(2000)])
    assert np.array_equal(one_by_one, nees_values(errors, cov))


def test_honest_covariance_passes_overconfident_fails():
    rng = np.random.default_rng(3)
    k = 4000
    a = rng.normal(size=(k, 2, 2))
    cov = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(2)  # random SPD covariances
    errors = np.einsum("kij,kj->ki", np.linalg.cholesky(cov), rng.normal(size=(k, 2)))  # e ~ N(0, P)
    honest = nees(errors, cov)
    assert honest["mean"] == pytest.approx(2.0, abs=0.15) and honest["consistent"]
    assert honest["fraction_inside"] == pytest.approx(0.95, abs=0.02)
    over = nees(errors, cov / 4.0)  # filter claims half the true standard deviation
    assert over["mean"] == pytest.approx(8.0, rel=0.1) and not over["consistent"]
    assert over["fraction_inside"] < 0.8


def _greedy_match_walk(dist, rank, threshold_m):
    """The devkit's greedy matching as a plain walk over every prediction (the reference)."""
    tp, taken = np.zeros(dist.shape[0], dtype=bool), np.zeros(dist.shape[1], dtype=bool)
    for p in np.argsort(rank, kind="stable"):
        row = np.where(taken, np.inf, dist[p])
        if dist.shape[1] and row[int(np.argmin(row))] < threshold_m:
            taken[int(np.argmin(row))] = tp[p] = True
    return tp


def test_greedy_match_equals_the_plain_walk():
    rng = np.random.default_rng(7)
    for _ in range(3000):
        n_pred, n_truth = rng.integers(0, 9), rng.integers(0, 9)
        # coarse values: many ties, shared nearest truths and distances at the threshold
        dist = rng.integers(0, 6, size=(n_pred, n_truth)) * 0.5
        rank = rng.permutation(n_pred)
        for threshold_m in (0.5, 1.0, 2.0, 4.0):
            assert _greedy_match(dist, rank, threshold_m).tolist() == _greedy_match_walk(dist, rank, threshold_m).tolist()


def test_greedy_matches_at_every_threshold_equal_the_plain_walk():
    """_greedy_matches (one call for all thresholds, shared nearest truths checked once at the
    widest) gives each threshold's walk; unsorted thresholds too."""
    rng = np.random.default_rng(8)
    for _ in range(2000):
        n_pred, n_truth = rng.integers(0, 9), rng.integers(0, 9)
        dist = rng.integers(0, 10, size=(n_pred, n_truth)) * rng.choice([0.25, 0.5, 1.0])
        rank = rng.permutation(n_pred)
        thresholds = tuple(rng.permutation([0.5, 1.0, 2.0, 4.0]))
        got = _greedy_matches(dist, rank, thresholds)
        assert [g.tolist() for g in got] == [_greedy_match_walk(dist, rank, th).tolist() for th in thresholds]


def test_compiled_frame_flags_equal_the_greedy_matches_per_bin():
    """Every frame's flag words and truth counts, bit for bit, on generated frames (ties within a frame,
    tied rivals, every bin edge) and on coarse grids (tied distances at the thresholds)."""
    rng = np.random.default_rng(21)
    frames = [(t.xy, p.xy, p.confidence) for t, p in generated_frames(rng, 400)]
    for _ in range(400):
        truth_xy = rng.integers(-40, 40, (rng.integers(0, 9), 2)) * 2.5
        pred_xy = rng.integers(-40, 40, (rng.integers(0, 9), 2)) * 2.5 + rng.choice([0.0, 0.5, 1.0], (1, 2))
        frames.append((truth_xy, pred_xy, np.round(rng.random(len(pred_xy)), 1)))
    matched = 0
    for kw in ({}, {"range_bins_m": [(0.0, 20.0), (10.0, 45.0), (0.0, math.inf)], "thresholds_m": (1.0, 0.5, 2.5)}):
        ap = CenterDistanceAp(**kw)
        for truth_xy, pred_xy, confidence in frames:
            cost = center_distance_cost(truth_xy, pred_xy) if len(truth_xy) and len(pred_xy) else \
                np.zeros((len(truth_xy), len(pred_xy)))
            d_truth, d_pred = np.hypot(truth_xy[:, 0], truth_xy[:, 1]), np.hypot(pred_xy[:, 0], pred_xy[:, 1])
            flags, truths = _frame_flags(cost, d_truth, d_pred, _confidence_order(confidence), *ap._bins)
            assert (flags.tolist(), truths.tolist()) == frame_flags_reference(ap, truth_xy, pred_xy, confidence)
            matched += sum(bin(f).count("1") for f in flags.tolist())
    assert matched > 5000


def test_streaming_ap_refuses_costs_or_confidences_of_other_shapes():
    ap, truth, pred = CenterDistanceAp(), np.zeros((3, 2)), np.ones((2, 2))
    with pytest.raises(ValueError):
        ap.add_frame(truth, pred, np.ones(2), np.zeros((2, 3)))
    with pytest.raises(ValueError):
        ap.add_frame(truth, pred, np.ones(3))
    ap.add_frame(truth, pred, np.ones(2), np.zeros((3, 2)))
