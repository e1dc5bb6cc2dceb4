"""The faster frame changes equal the expressions they replace, bit for bit.

References: ``v2i.core.frames`` before the kept axes (``_Axes``: R(yaw), the origin and the zero velocity
offset per pose), and ``predict_ca`` before its shared step (``motion.ca_step``).
"""

import numpy as np
import pytest

from v2i.core import frames
from v2i.core.frames import Pose2D, PoseUncertainty, add_pose_uncertainty, base_to_map, map_to_base
from v2i.fusion.motion import predict_ca
from v2i.core.objects import ObjectArray

_S = np.array([[0.0, -1.0], [1.0, 0.0]])
_COLUMNS = ("ids", "cls", "xy", "z", "lwh", "yaw", "vxy", "axy", "yaw_rate", "cov_xy", "confidence", "cov_vxy",
            "age_s", "sources")


# --- the previous expressions ------------------------------------------------------------------------------
def _wrap_ref(rad):
    return (np.asarray(rad) + np.pi) % (2.0 * np.pi) - np.pi


def _rotation_ref(yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


def _pose_cov_map_ref(xy_m, ego, cov):
    d = (np.asarray(xy_m, dtype=float) - [ego.x, ego.y]).reshape(-1, 2)
    jac = np.zeros((len(d), 2, 3))
    jac[:, 0, 0] = jac[:, 1, 1] = 1.0
    jac[:, :, 2] = d @ _S.T
    return jac @ np.asarray(cov, dtype=float) @ jac.transpose(0, 2, 1)


def _add_pose_uncertainty_ref(objs, ego, vel_offset=None):
    if ego.uncertainty is None or not len(objs):
        return objs
    sigma = ego.uncertainty.cov
    sv = (objs.vxy - (0.0 if vel_offset is None else vel_offset)) @ _S.T
    return objs.with_(cov_xy=objs.cov_xy + _pose_cov_map_ref(objs.xy, ego, sigma),
                      cov_vxy=objs.cov_vxy + sigma[2, 2] * sv[:, :, None] * sv[:, None, :])


def _transform_ref(objs, rot, xy, dyaw, vel_offset):
    return objs.with_(xy=xy, yaw=_wrap_ref(objs.yaw + dyaw), vxy=objs.vxy @ rot.T - vel_offset, axy=objs.axy @ rot.T,
                      cov_xy=rot @ objs.cov_xy @ rot.T, cov_vxy=rot @ objs.cov_vxy @ rot.T)


def _map_to_base_ref(objs, ego, relative_velocity=False, pose_uncertainty=True):
    ego_v_map = np.array([ego.vx, ego.vy]) if relative_velocity else np.zeros(2)
    if pose_uncertainty:
        objs = _add_pose_uncertainty_ref(objs, ego, ego_v_map)
    rot = _rotation_ref(ego.yaw).T
    xy = (np.asarray(objs.xy, dtype=float) - [ego.x, ego.y]) @ _rotation_ref(ego.yaw)
    return _transform_ref(objs, rot, xy, -ego.yaw, rot @ ego_v_map)


def _base_to_map_ref(objs, ego, pose_uncertainty=True):
    xy = np.asarray(objs.xy, dtype=float) @ _rotation_ref(ego.yaw).T + [ego.x, ego.y]
    out = _transform_ref(objs, _rotation_ref(ego.yaw), xy, ego.yaw, np.zeros(2))
    return _add_pose_uncertainty_ref(out, ego) if pose_uncertainty else out


def _predict_ca_ref(objs, dt_s):
    if isinstance(dt_s, (float, int)):
        dt, zero = np.float64(dt_s), np.float64(0.0)
        return objs.with_(xy=objs.xy + objs.vxy * dt + 0.5 * objs.axy * (dt * dt), vxy=objs.vxy + objs.axy * dt,
                          age_s=objs.age_s + max(dt, zero))
    dt = np.broadcast_to(np.asarray(dt_s, dtype=float), (len(objs),))[:, None]
    return objs.with_(xy=objs.xy + objs.vxy * dt + 0.5 * objs.axy * dt**2, vxy=objs.vxy + objs.axy * dt,
                      age_s=objs.age_s + np.maximum(dt[:, 0], 0.0))


def _objects(rng, n, zero_velocity=False):
    a = rng.normal(size=(n, 2, 2))
    b = rng.normal(size=(n, 2, 2))
    vxy = np.zeros((n, 2)) if zero_velocity else rng.normal(0, 8, (n, 2))
    xy = rng.uniform(-300, 300, (n, 2))
    if n and not zero_velocity:
        vxy[0] = xy[0] = 0.0  # a standing object among moving ones, at the origin (a rounding shows in each term)
    return ObjectArray(ids=np.arange(n), cls=rng.integers(0, 4, n), xy=xy,
                       z=rng.normal(size=n), lwh=rng.uniform(1, 5, (n, 3)), yaw=rng.uniform(-7, 7, n), vxy=vxy,
                       axy=rng.normal(0, 2, (n, 2)), cov_xy=a @ a.transpose(0, 2, 1) + 0.01 * np.eye(2),
                       cov_vxy=b @ b.transpose(0, 2, 1) + 0.01 * np.eye(2), age_s=rng.uniform(0, 3, n))


def _ego(rng, uncertain=True, yaw=None):
    unc = PoseUncertainty(np.diag(rng.uniform(1e-4, 1e-2, 3)), 5.0) if uncertain else None
    return Pose2D(np.float64(rng.uniform(-100, 100)), float(rng.uniform(-100, 100)),
                  float(rng.uniform(-np.pi, np.pi)) if yaw is None else yaw, float(rng.normal(0, 5)),
                  float(rng.normal(0, 5)), unc)


def _assert_same(a, b, columns=_COLUMNS):
    for name in columns:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert x.tobytes() == y.tobytes(), name


_YAWS = (None, 0.0, -0.0, np.pi, -np.pi, np.pi / 2, 3 * np.pi / 4, -3 * np.pi / 4)


@pytest.mark.parametrize("seed", range(6))
def test_frame_changes_equal_the_previous_expressions(seed):
    rng = np.random.default_rng(seed)
    for n in (0, 1, 2, 5, 13):
        for yaw in _YAWS:
            for uncertain in (True, False):
                objs, ego = _objects(rng, n, zero_velocity=n == 2), _ego(rng, uncertain, yaw)
                for relative in (False, True):
                    for pose in (False, True):
                        _assert_same(map_to_base(objs, ego, relative, pose), _map_to_base_ref(objs, ego, relative, pose))
                for pose in (False, True):
                    _assert_same(base_to_map(objs, ego, pose), _base_to_map_ref(objs, ego, pose))
                _assert_same(add_pose_uncertainty(objs, ego), _add_pose_uncertainty_ref(objs, ego))
                offset = rng.normal(size=2)
                _assert_same(add_pose_uncertainty(objs, ego, offset), _add_pose_uncertainty_ref(objs, ego, offset))
                assert frames.map_to_base_points(objs.xy, ego).tobytes() == \
                    ((objs.xy - [ego.x, ego.y]) @ _rotation_ref(ego.yaw)).tobytes()
                assert frames.base_to_map_points(objs.xy, ego).tobytes() == \
                    (objs.xy @ _rotation_ref(ego.yaw).T + [ego.x, ego.y]).tobytes()
                if uncertain:
                    cov = ego.uncertainty.cov
                    assert frames.pose_cov_map(objs.xy, ego, cov).tobytes() == \
                        _pose_cov_map_ref(objs.xy, ego, cov).tobytes()


def test_kept_axes_follow_the_pose_asked_about():
    """The axes are kept per pose object: another pose (even an equal one) gets its own, and a pose's yaw of
    -0.0 is not taken for 0.0 (R(-0.0) has a -0.0 sine)."""
    objs = _objects(np.random.default_rng(7), 4)
    first, turned = Pose2D(1.0, 2.0, 0.3), Pose2D(1.0, 2.0, 1.3)
    _assert_same(map_to_base(objs, first), _map_to_base_ref(objs, first))
    _assert_same(map_to_base(objs, turned), _map_to_base_ref(objs, turned))
    moved = Pose2D(5.0, -2.0, 0.3)
    _assert_same(base_to_map(objs, moved), _base_to_map_ref(objs, moved))
    for yaw in (0.0, -0.0):
        ego = Pose2D(0.0, 0.0, yaw)
        _assert_same(map_to_base(objs, ego), _map_to_base_ref(objs, ego))
    with pytest.raises(ValueError):
        frames._axes(first).rot[0, 0] = 2.0  # shared: read-only


def test_predict_ca_equals_the_previous_expression():
    rng = np.random.default_rng(11)
    for n in (0, 1, 6):
        objs = _objects(rng, n)
        for dt in (0.0, -0.0, 0.137, -0.02, 3, float(rng.uniform(0, 1)), rng.uniform(-1, 1, n)):
            _assert_same(predict_ca(objs, dt), _predict_ca_ref(objs, dt))
