import numpy as np
import pytest

from v2i.core.frames import (Pose2D, PoseUncertainty, base_to_map, base_to_map_points, map_to_base, map_to_base_points,
                          pose_jacobian, rotation)
from v2i.fusion.motion import predict_ca, predict_cv
from v2i.core.objects import ObjectArray
from v2i.fusion.pose_history import PoseHistory


def one(x, y, yaw=0.0, vx=0.0, vy=0.0):
    return ObjectArray(ids=np.array([1]), cls=np.array([1]), xy=np.array([[x, y]], float), z=np.zeros(1),
                       lwh=np.array([[4.0, 2.0, 1.5]]), yaw=np.array([yaw]), vxy=np.array([[vx, vy]], float))


def test_map_to_base_known_example():
    # ego at (10, 5) facing north: a point 3 m north of it is 3 m ahead (x), one 2 m west is 2 m left (y)
    ego = Pose2D(10.0, 5.0, np.pi / 2)
    np.testing.assert_allclose(map_to_base_points([[10, 8], [8, 5]], ego), [[3, 0], [0, 2]], atol=1e-12)
    obj = map_to_base(one(10, 8, yaw=np.pi / 2, vx=0.0, vy=5.0), ego)
    np.testing.assert_allclose(obj.vxy, [[5.0, 0.0]], atol=1e-12)  # moving straight ahead
    assert obj.yaw[0] == pytest.approx(0.0)


def test_map_base_round_trip_preserves_everything():
    rng = np.random.default_rng(0)
    ego = Pose2D(*rng.normal(size=2), rng.uniform(-np.pi, np.pi))
    objs = one(3.0, -4.0, yaw=0.3, vx=1.0, vy=2.0).with_(cov_xy=np.array([[[2.0, 0.5], [0.5, 1.0]]]),
                                                          cov_vxy=np.array([[[0.3, -0.1], [-0.1, 0.2]]]))
    base = map_to_base(objs, ego)
    rot = np.array([[np.cos(ego.yaw), np.sin(ego.yaw)], [-np.sin(ego.yaw), np.cos(ego.yaw)]])  # R(yaw)^T
    np.testing.assert_allclose(base.cov_vxy[0], rot @ objs.cov_vxy[0] @ rot.T, atol=1e-12)
    back = base_to_map(base, ego)
    np.testing.assert_allclose(back.xy, objs.xy, atol=1e-12)
    np.testing.assert_allclose(back.vxy, objs.vxy, atol=1e-12)
    np.testing.assert_allclose(back.cov_xy, objs.cov_xy, atol=1e-12)
    np.testing.assert_allclose(back.cov_vxy, objs.cov_vxy, atol=1e-12)
    assert back.yaw[0] == pytest.approx(0.3)


def test_relative_velocity_subtracts_ego_motion():
    ego = Pose2D(0.0, 0.0, 0.0, vx=10.0)
    obj = map_to_base(one(20, 0, vx=10.0), ego, relative_velocity=True)
    np.testing.assert_allclose(obj.vxy, [[0.0, 0.0]])


def test_predict_cv_and_ca():
    o = one(0, 0, vx=2.0, vy=-1.0).with_(axy=np.array([[1.0, 0.0]]))
    np.testing.assert_allclose(predict_cv(o, 0.5).xy, [[1.0, -0.5]])
    ca = predict_ca(o, 2.0)
    np.testing.assert_allclose(ca.xy, [[2 * 2 + 0.5 * 1 * 4, -2.0]])
    np.testing.assert_allclose(ca.vxy, [[4.0, -1.0]])


def test_pose_history_interpolates_and_extrapolates():
    h = PoseHistory(horizon_s=1.0)
    h.add(1_000_000_000, Pose2D(0.0, 0.0, np.pi - 0.1, vx=1.0))
    h.add(1_200_000_000, Pose2D(2.0, 0.0, -np.pi + 0.1, vx=1.0))
    mid = h.at(1_100_000_000)
    assert mid.x == pytest.approx(1.0)
    assert abs(abs(mid.yaw) - np.pi) < 1e-9  # across the +-pi seam, not through 0
    assert h.at(1_300_000_000).x == pytest.approx(2.1)
    h.add(2_500_000_000, Pose2D(5.0, 0.0, 0.0))
    assert len(h) == 1  # older than the horizon is dropped


# --- pose uncertainty -------------------------------------------------------------------

SIGMA = np.diag([0.05**2, 0.08**2, 0.005**2])  # x m, y m, yaw rad


def test_pose_jacobian_matches_finite_differences_both_ways():
    rng = np.random.default_rng(1)
    ego = Pose2D(12.0, -7.0, 2.3)
    p_b = rng.uniform(-300, 300, (5, 2))
    p_m = base_to_map_points(p_b, ego)
    jac_m = pose_jacobian(p_m - [ego.x, ego.y])
    jac_b = -rotation(ego.yaw).T @ jac_m  # J_b = -R^T J_m (module docstring)
    h, num_m, num_b = 1e-6, np.zeros((5, 2, 3)), np.zeros((5, 2, 3))
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        plus, minus = (Pose2D(*(np.array([ego.x, ego.y, ego.yaw]) + sign * step)) for sign in (1, -1))
        num_m[:, :, k] = (base_to_map_points(p_b, plus) - base_to_map_points(p_b, minus)) / (2 * h)
        num_b[:, :, k] = (map_to_base_points(p_m, plus) - map_to_base_points(p_m, minus)) / (2 * h)
    np.testing.assert_allclose(jac_m, num_m, atol=1e-6)
    np.testing.assert_allclose(jac_b, num_b, atol=1e-6)
    np.testing.assert_allclose(np.abs(jac_m[:, :, 2]), np.abs(p_m - [ego.x, ego.y])[:, ::-1])  # the lever arm
    # the covariance the transforms add is J Sigma J^T with the numerical Jacobians
    uncertain = Pose2D(ego.x, ego.y, ego.yaw, uncertainty=PoseUncertainty(SIGMA))
    exact = np.zeros((5, 2, 2))
    to_base = map_to_base(ObjectArray.concat([one(*p).with_(cov_xy=exact[:1]) for p in p_m]), uncertain)
    to_map = base_to_map(ObjectArray.concat([one(*p).with_(cov_xy=exact[:1]) for p in p_b]), uncertain)
    np.testing.assert_allclose(to_base.cov_xy, num_b @ SIGMA @ num_b.transpose(0, 2, 1), rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(to_map.cov_xy, num_m @ SIGMA @ num_m.transpose(0, 2, 1), rtol=1e-6, atol=1e-12)


def test_map_to_base_adds_the_lever_arm_and_the_velocity_turn():
    ego = Pose2D(0.0, 0.0, 0.0, uncertainty=PoseUncertainty(SIGMA))
    obj = one(300.0, 0.0, vx=10.0).with_(cov_xy=np.eye(2)[None] * 0.25, cov_vxy=np.eye(2)[None] * 0.04)
    out = map_to_base(obj, ego)
    # dead ahead at 300 m: x gains sigma_x^2, y gains sigma_y^2 + (300 sigma_yaw)^2 = 0.0064 + 2.25
    np.testing.assert_allclose(out.cov_xy[0], [[0.25 + 0.0025, 0.0], [0.0, 0.25 + 0.0064 + 2.25]], atol=1e-12)
    np.testing.assert_allclose(out.cov_vxy[0], [[0.04, 0.0], [0.0, 0.04 + (10 * 0.005) ** 2]], atol=1e-12)
    rel = map_to_base(obj, Pose2D(0.0, 0.0, 0.0, vx=10.0, uncertainty=PoseUncertainty(SIGMA)), relative_velocity=True)
    np.testing.assert_allclose(rel.cov_vxy[0], np.eye(2) * 0.04, atol=1e-12)  # v - v_ego = 0 does not turn
    exact = map_to_base(obj, ego, pose_uncertainty=False)
    np.testing.assert_allclose(exact.cov_xy, obj.cov_xy)
    assert ego == Pose2D(0.0, 0.0, 0.0)  # the uncertainty is not part of the pose's identity


def _mc_nees(errors, covs):
    return float(np.mean(np.einsum("ki,ki->k", errors, np.linalg.solve(covs, errors[:, :, None])[:, :, 0])))


def test_monte_carlo_nees_of_rsu_objects_moved_with_a_noisy_pose():
    """An object known in map (error C_m) moved into the base_link of a pose estimate with
    error ~ N(0, Sigma) and scored in the true base_link: NEES ~ 2 only with the pose term."""
    rng = np.random.default_rng(2)
    n = 5000
    true_ego = Pose2D(40.0, 10.0, 0.7)
    p_m = base_to_map_points(np.array([[350.0, 60.0]]), true_ego)[0]
    c_m = np.array([[0.5, 0.1], [0.1, 0.3]])
    pose_err = rng.multivariate_normal(np.zeros(3), SIGMA, n)
    meas_m = p_m + rng.multivariate_normal(np.zeros(2), c_m, n)
    truth_b = map_to_base_points(p_m[None], true_ego)[0]
    errors, covs, naive = np.zeros((n, 2)), np.zeros((n, 2, 2)), np.zeros((n, 2, 2))
    for i in range(n):
        est = Pose2D(true_ego.x + pose_err[i, 0], true_ego.y + pose_err[i, 1], true_ego.yaw + pose_err[i, 2],
                     uncertainty=PoseUncertainty(SIGMA))
        out = map_to_base(one(*meas_m[i]).with_(cov_xy=c_m[None]), est)
        errors[i], covs[i] = out.xy[0] - truth_b, out.cov_xy[0]
        naive[i] = map_to_base(one(*meas_m[i]).with_(cov_xy=c_m[None]), est, pose_uncertainty=False).cov_xy[0]
    assert 1.9 < _mc_nees(errors, covs) < 2.1
    assert _mc_nees(errors, naive) > 5.0  # the lateral lever arm, 355 m * 0.005 rad = 1.8 m, dwarfs C_m


def test_outside_box_rows_are_the_points_outside_the_ego_box():
    """Points around a turned ego: inside the box (base_link |x| <= half_l, |y| <= half_w), near its corner,
    just past them and far away; the rows outside, ascending, as int64."""
    from v2i.core.frames import outside_box_rows

    ego = Pose2D(12.5, -3.0, 0.7)
    base = np.array([[1.0, 0.2], [5.0, 0.0], [-2.3, 0.85], [2.4, 0.0], [0.0, -0.95], [-300.0, 40.0], [0.0, 0.0]])
    got = outside_box_rows(base_to_map_points(base, ego), ego, 2.35, 0.9)
    assert got.dtype == np.int64 and got.tolist() == [1, 3, 4, 5]
    assert outside_box_rows(np.zeros((0, 2)), ego, 2.35, 0.9).tolist() == []
