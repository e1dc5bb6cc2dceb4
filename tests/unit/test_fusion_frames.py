import numpy as np
import pytest

from fusion.frames import (Pose2D, PoseUncertainty, base_to_map, base_to_map_points, map_to_base, map_to_base_points,
                          pose_jacobian, rotation)
from fusion.motion import predict_ca, predict_cv
from fusion.objects import ObjectArray
from fusion.pose_history import PoseHistory


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


def _outside_reference(xy, ego, half_l, half_w):
    """The numpy expression outside_box_rows replaces (admission.not_ego's before it)."""
    local = map_to_base_points(xy, ego)
    return np.flatnonzero(~((np.abs(local[:, 0]) <= half_l) & (np.abs(local[:, 1]) <= half_w)))


def _edge_points(rng, ego, half_l, half_w, n):
    """Points whose base_link coordinate lies on an edge of the box, or an ulp or two either side."""
    along = rng.uniform(-1.5, 1.5, n)
    sx, sy = rng.choice([-1.0, 1.0], n), rng.choice([-1.0, 1.0], n)
    on_x = np.column_stack([sx * half_l, along * half_w])
    on_y = np.column_stack([along * half_l, sy * half_w])
    base = np.concatenate([on_x, on_y])
    for k in range(rng.integers(0, 3)):  # nudged by a few ulps
        base = np.nextafter(base, rng.choice([-np.inf, np.inf], base.shape))
    return base_to_map_points(base, ego)


def test_outside_box_rows_equal_the_numpy_expression_bit_for_bit():
    """The compiled pass decides every point off the edges as numpy's matmul does, and hands points on
    (or an ulp from) an edge, NaN and inf to the numpy expression: the same rows on random and edge
    points, signed zeros, yaws of +-pi, +-0 and far egos (fails with a slack of 0)."""
    from fusion.frames import _outside_rows, outside_box_rows

    rng = np.random.default_rng(11)
    decided = fallbacks = 0
    yaws = [np.pi, -np.pi, 0.0, -0.0, np.pi / 2, -np.pi / 2, np.nextafter(np.pi, 0.0)]
    for trial in range(3000):
        yaw = yaws[trial] if trial < len(yaws) else rng.uniform(-np.pi, np.pi)
        centre = rng.uniform(-2000.0, 2000.0, 2) if trial % 3 else np.array([-0.0, 0.0])
        ego = Pose2D(float(centre[0]), float(centre[1]), float(yaw))
        half_l, half_w = rng.uniform(0.5, 4.0), rng.uniform(0.3, 2.0)
        n = int(rng.integers(1, 30))
        xy = centre + rng.normal(0.0, rng.choice([1.0, 5.0, 300.0]), (n, 2))
        if trial % 4 == 1:
            xy = np.concatenate([xy, _edge_points(rng, ego, half_l, half_w, 3)])
        if trial % 50 == 7:
            xy[0] = [np.nan, 1.0] if trial % 100 == 7 else [np.inf, -np.inf]
        if trial % 10 == 3:
            xy[0] = [-0.0, 0.0]
            xy[-1] = centre  # the ego's own centre
        with np.errstate(invalid="ignore"):  # inf - inf in the matmul of the inf rows: NaN, as meant
            want = _outside_reference(xy, ego, half_l, half_w)
            got = outside_box_rows(xy, ego, half_l, half_w)
        assert got.dtype == np.int64 and np.array_equal(got, want), trial
        m = _outside_rows(xy, ego.x, ego.y, np.cos(ego.yaw), np.sin(ego.yaw), half_l, half_w,
                          np.empty(len(xy), np.int64))
        decided, fallbacks = decided + (m >= 0), fallbacks + (m < 0)
    assert decided > 2000 and fallbacks > 100  # both paths taken


def test_outside_box_rows_hands_edge_points_to_numpy():
    from fusion.frames import _outside_rows

    ego = Pose2D(12.5, -3.0, 0.7)
    on_edge = base_to_map_points(np.array([[2.35, 0.1]]), ego)  # x_b on the edge (within rounding)
    assert _outside_rows(on_edge, ego.x, ego.y, np.cos(ego.yaw), np.sin(ego.yaw), 2.35, 0.9,
                         np.empty(1, np.int64)) == -1
    assert _outside_rows(np.array([[np.nan, 0.0]]), 0.0, 0.0, 1.0, 0.0, 2.35, 0.9, np.empty(1, np.int64)) == -1
    inside = base_to_map_points(np.array([[1.0, 0.2], [5.0, 0.0]]), ego)
    keep = np.empty(2, np.int64)
    assert _outside_rows(inside, ego.x, ego.y, np.cos(ego.yaw), np.sin(ego.yaw), 2.35, 0.9, keep) == 1 and keep[0] == 1
