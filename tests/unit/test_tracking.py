import numpy as np
import pytest

from fusion.association import assign, center_distance_cost
from fusion.objects import ObjectArray
from fusion.tracking import Tracker, TrackerConfig


def dets(xy, cls=1, std=0.5):
    xy = np.atleast_2d(np.asarray(xy, float))
    n = len(xy)
    return ObjectArray(ids=np.full(n, -1), cls=np.full(n, cls), xy=xy, z=np.zeros(n), lwh=np.tile([4.5, 1.8, 1.5], (n, 1)),
                       yaw=np.zeros(n), vxy=np.zeros((n, 2)), cov_xy=np.tile(np.eye(2) * std**2, (n, 1, 1)))


def test_assign_respects_gate_and_classes():
    cost = center_distance_cost(np.array([[0, 0], [10, 0]]), np.array([[0.5, 0], [30, 0]]), [1, 1], [1, 1])
    result = assign(cost, gate=2.0)
    assert result.matches.tolist() == [[0, 0]]
    assert result.unmatched_a.tolist() == [1] and result.unmatched_b.tolist() == [1]
    cross = center_distance_cost(np.array([[0, 0]]), np.array([[0.1, 0]]), [1], [5])
    assert len(assign(cross, gate=2.0).matches) == 0


def test_tracker_estimates_velocity_and_keeps_ids():
    rng = np.random.default_rng(1)
    tracker = Tracker(TrackerConfig())
    out = None
    for k in range(25):
        t = 0.2 * k
        truth = np.array([[-80 + 13.9 * t, -5.25], [20.0, 30.0]])
        out = tracker.step(dets(truth + rng.normal(0, 0.5, truth.shape)), t)
    assert len(out) == 2
    moving = out.take(np.argmin(out.xy[:, 1]))
    assert moving.vxy[0, 0] == pytest.approx(13.9, abs=1.0)
    assert abs(moving.vxy[0, 1]) < 1.0
    assert sorted(out.ids.tolist()) == [1, 2]


def test_tracker_life_cycle():
    tracker = Tracker(TrackerConfig(confirm_hits=2, max_coast_s=0.5))
    assert len(tracker.step(dets([0, 0]), 0.0)) == 0  # tentative
    assert len(tracker.step(dets([0, 0]), 0.2)) == 1  # confirmed
    assert len(tracker.step(dets(np.zeros((0, 2))), 0.4)) == 1  # coasting
    assert len(tracker.step(dets(np.zeros((0, 2))), 0.8)) == 0  # deleted
    assert len(tracker) == 0
