import numpy as np
import pytest

from fusion.frames import Pose2D, base_to_map, map_to_base, map_to_base_points
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
