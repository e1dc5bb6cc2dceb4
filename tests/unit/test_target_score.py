"""score_target: the target's NEES tells an honest stated covariance from an overconfident one;
the target is scored in cycle order, whatever order the outputs arrive in."""

import numpy as np
import pytest

from v2i.scoring.metrics import MATCH_GATE_M, _match_target_xy, score_target
from v2i.fusion.association import assign, center_distance_cost
from v2i.core.frames import Pose2D
from v2i.core.objects import ObjectArray
from v2i.fusion.wire import states_from_objects
from schemas.messages import FusedObjectList

T0 = 1_767_225_600 * 10**9
CYCLES = 400


def car(xy, cov=None, ids=(7,)):
    xy = np.atleast_2d(xy)
    n = len(xy)
    return ObjectArray(ids=np.array(ids), cls=np.ones(n, int), xy=xy, z=np.full(n, 0.75),
                       lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=np.zeros(n), vxy=np.zeros((n, 2)),
                       cov_xy=np.eye(2)[None] if cov is None else cov[None])


class World:
    """The ego at the origin, facing +x; the target (id 7) drives along x at 10 m/s."""

    target_id = 7

    def ego_at(self, t_s):
        return Pose2D(0.0, 0.0, 0.0)

    def actors_at(self, t_s):
        return car([10.0 + 10.0 * t_s, 2.0])


def outputs(true_cov, stated_cov, seed=0):
    rng, world, out = np.random.default_rng(seed), World(), []
    for k in range(CYCLES):
        t_ns = T0 + k * 100_000_000
        truth = world.actors_at(k * 0.1).xy[0]
        est = car(truth + rng.multivariate_normal([0.0, 0.0], true_cov), stated_cov).with_(sources=np.array([1]))
        out.append(FusedObjectList(vehicle_id="car", seq=k, cycle_time_ns=t_ns, publish_time_ns=t_ns,
                                   objects=states_from_objects(est, fused=True)))
    return out


def test_target_nees_is_two_for_an_honest_covariance_and_larger_for_an_overconfident_one():
    cov = np.array([[0.09, 0.02], [0.02, 0.04]])
    honest = score_target(World(), outputs(cov, cov), T0)
    overconfident = score_target(World(), outputs(cov, cov / 4), T0)
    assert honest.detected_cycles == CYCLES
    assert 1.6 < honest.nees_mean < 2.4 and 0.9 < honest.nees_fraction_inside <= 1.0
    assert overconfident.nees_mean > 6.0 and overconfident.nees_fraction_inside < 0.7
    assert honest.rmse_m == overconfident.rmse_m  # same errors, only the stated covariance differs


def test_target_is_scored_in_cycle_order_whatever_the_arrival_order():
    cov = np.array([[0.09, 0.02], [0.02, 0.04]])
    outs = [m.model_copy(update={"objects": ()}) if m.seq < 50 else m for m in outputs(cov, cov)]  # seen from cycle 50
    in_order = score_target(World(), outs, T0)
    shuffled = [outs[i] for i in np.random.default_rng(1).permutation(len(outs))]
    assert score_target(World(), shuffled, T0) == in_order  # same bits: means taken in cycle order
    assert in_order.detected_cycles == CYCLES - 50
    assert in_order.first_detection_time_s == 5.0
    assert in_order.first_detection_distance_m == pytest.approx(np.hypot(60.0, 2.0))


def test_target_match_shortcut_equals_the_full_assignment():
    """metrics._match_target_xy's isolated-pair shortcut gives the index of the full matching."""
    rng = np.random.default_rng(3)
    for _ in range(2000):
        n_truth, n_out = rng.integers(1, 7), rng.integers(1, 7)
        truth_xy = rng.uniform(0.0, 12.0, (n_truth, 2)).round(0)  # coarse: shared and tied neighbours
        out_xy = truth_xy[rng.integers(0, n_truth, n_out)] + rng.normal(0.0, 2.5, (n_out, 2))
        ids = rng.permutation(n_truth) + 10
        result = assign(center_distance_cost(truth_xy, out_xy), MATCH_GATE_M)
        rows = result.matches[ids[result.matches[:, 0]] == 10]
        assert _match_target_xy(truth_xy, ids, out_xy, 10) == (int(rows[0, 1]) if len(rows) else None)
