"""Localisation uncertainty through the OBU: stated by the simulated localisation, kept by the
pose history, added where RSU objects meet the ego's frame, and not double counted for own
detections (Monte-Carlo NEES against the true base_link)."""

import numpy as np
import pytest

from v2i.fusion.ego_map_tracker import EgoMapTracker
from v2i.core.frames import (Pose2D, PoseUncertainty, add_pose_uncertainty, base_to_map, base_to_map_points, map_to_base,
                          pose_cov_map, rotation)
from v2i.core.objects import ObjectArray
from v2i.fusion.pose_history import PoseHistory
from v2i.fusion.tracking import Tracker, TrackerConfig
from obu_service.methods import RsuFrame, make_fusion
from schemas.messages import SOURCE_RSU, SOURCE_VEHICLE
from v2i.sim.scenario import LocalizationConfig
from v2i.sim.sensors import Localization

SIGMA = np.diag([0.05**2, 0.05**2, 0.005**2])


class _StillWorld:
    """The ego standing at the origin facing +x (all Localization reads of a World)."""

    def ego_at(self, t_s):
        return Pose2D(0.0, 0.0, 0.0)


def points(xy, cov_xy, vxy=None, cov_vxy=None, src=SOURCE_VEHICLE):
    xy = np.atleast_2d(np.asarray(xy, float))
    n = len(xy)
    return ObjectArray(ids=np.arange(n), cls=np.ones(n, np.int64), xy=xy, z=np.zeros(n),
                       lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=np.zeros(n),
                       vxy=np.zeros((n, 2)) if vxy is None else np.atleast_2d(vxy).astype(float),
                       cov_xy=np.broadcast_to(cov_xy, (n, 2, 2)).copy(),
                       cov_vxy=None if cov_vxy is None else np.broadcast_to(cov_vxy, (n, 2, 2)).copy(),
                       sources=np.full(n, src))


def _nees(errors, covs):
    e = np.asarray(errors)
    return float(np.mean(np.einsum("ki,ki->k", e, np.linalg.solve(np.asarray(covs), e[:, :, None])[:, :, 0])))


def test_localization_states_the_statistics_of_its_own_errors():
    cfg = LocalizationConfig(x_std_m=0.05, y_std_m=0.08, yaw_std_rad=0.005, correlation_time_s=5.0)
    rng, world, n = np.random.default_rng(3), _StillWorld(), 6000
    errors = np.zeros((n, 3, 3))  # instance, time (0, 0.1, 1.0 s), (x, y, yaw)
    for i in range(n):
        loc = Localization(cfg, rng)
        for k, t_s in enumerate((0.0, 0.1, 1.0)):
            p = loc.measure(world, t_s)
            errors[i, k] = p.x, p.y, p.yaw
    stated = p.uncertainty
    np.testing.assert_allclose(stated.cov, np.diag([0.05**2, 0.08**2, 0.005**2]))
    assert stated.correlation_time_s == 5.0
    for got, want in ((errors[:, 0], stated.cov), (errors[:, 1] - errors[:, 0], stated.drift_cov(0.1)),
                      (errors[:, 2] - errors[:, 1], stated.drift_cov(0.9))):
        np.testing.assert_allclose(np.diag(np.cov(got.T)), np.diag(want), rtol=0.08)
    assert stated.drift_cov(0.1)[2, 2] == pytest.approx(2 * (1 - np.exp(-0.02)) * 0.005**2)
    assert PoseUncertainty(SIGMA).drift_cov(0.1) == pytest.approx(2 * SIGMA)  # tau 0: white errors
    with pytest.raises(ValueError, match="3x3"):
        PoseUncertainty(np.eye(2))


def test_pose_history_interpolates_the_uncertainty_within_the_bound():
    u_p, u_q = PoseUncertainty(SIGMA, 5.0), PoseUncertainty(4 * SIGMA, 5.0)
    h = PoseHistory()
    h.add(0, Pose2D(0.0, 0.0, 0.0, uncertainty=u_p))
    h.add(100_000_000, Pose2D(1.0, 0.0, 0.0, uncertainty=u_q))
    mid = h.at(25_000_000).uncertainty
    np.testing.assert_allclose(mid.cov, 0.75 * SIGMA + 0.25 * 4 * SIGMA)
    assert h.at(300_000_000).uncertainty is u_q  # extrapolation keeps the last one
    # the blend bounds the covariance of (1 - a) e_p + a e_q for any correlation of e_p and e_q
    rng = np.random.default_rng(4)
    for _ in range(50):
        a_ = rng.uniform()
        root = rng.normal(size=(6, 6))
        joint = root @ root.T  # a random joint covariance of (e_p, e_q)
        mix = np.hstack([(1 - a_) * np.eye(3), a_ * np.eye(3)])
        blend = (1 - a_) * joint[:3, :3] + a_ * joint[3:, 3:]
        assert np.linalg.eigvalsh(blend - mix @ joint @ mix.T).min() > -1e-9


def test_monte_carlo_own_and_rsu_fused_in_the_ego_map_are_not_double_counted():
    """Own detection (true base_link) and RSU object (true map) fused in the ego's map':
    the pose term on the RSU leg only gives NEES ~ 2; on every leg it double counts."""
    rng, n = np.random.default_rng(5), 3000
    true_ego = Pose2D(20.0, -5.0, 0.4)
    truth_b = np.array([70.0, 15.0])
    truth_m = base_to_map_points(truth_b[None], true_ego)[0]
    c_own, c_rsu = np.eye(2) * 0.15**2, np.diag([0.4, 0.25])
    errors, covs, counted_twice = [], [], []
    for d in rng.multivariate_normal(np.zeros(3), SIGMA, n):
        est = Pose2D(true_ego.x + d[0], true_ego.y + d[1], true_ego.yaw + d[2], uncertainty=PoseUncertainty(SIGMA))
        own = points(truth_b + rng.multivariate_normal(np.zeros(2), c_own), c_own)
        rsu = points(truth_m + rng.multivariate_normal(np.zeros(2), c_rsu), c_rsu, src=SOURCE_RSU)
        for legs, sink in ((False, None), (True, counted_twice)):
            a, b = base_to_map(own, est, pose_uncertainty=legs), add_pose_uncertainty(rsu, est)
            info = np.linalg.inv(a.cov_xy[0]) + np.linalg.inv(b.cov_xy[0])
            p = np.linalg.inv(info)  # P = (P_a^-1 + P_b^-1)^-1, x = P (P_a^-1 x_a + P_b^-1 x_b)
            x = p @ (np.linalg.solve(a.cov_xy[0], a.xy[0]) + np.linalg.solve(b.cov_xy[0], b.xy[0]))
            out = map_to_base(points(x, p), est, pose_uncertainty=legs)
            if sink is None:
                errors.append(out.xy[0] - truth_b)
                covs.append(out.cov_xy[0])
            else:
                sink.append(out.cov_xy[0])
    assert 1.85 < _nees(errors, covs) < 2.15
    assert _nees(errors, counted_twice) < 1.2


def _track_nees(tracker_cls, runs: int, cycles: int, range_m: float) -> float:
    """A still object range_m ahead, seen by own LiDAR every 0.1 s from an ego whose pose
    estimate has a Gauss-Markov error; NEES of the last output in the true base_link."""
    cfg = LocalizationConfig(x_std_m=0.05, y_std_m=0.05, yaw_std_rad=0.005, correlation_time_s=5.0)
    rng, world, errors, covs = np.random.default_rng(6), _StillWorld(), [], []
    truth_b = np.array([range_m, 0.0])
    for _ in range(runs):
        loc, tracker = Localization(cfg, rng), tracker_cls(TrackerConfig(accel_std_mps2=1.0))
        for k in range(cycles):
            t_s, est = 0.1 * k, loc.measure(world, 0.1 * k)
            tracker.ego = est
            det = points(truth_b + rng.normal(0.0, 0.1, 2), np.eye(2) * 0.01, rng.normal(0.0, 0.3, 2), np.eye(2) * 0.09)
            tracker.predict(t_s)
            tracker.update(base_to_map(det, est, pose_uncertainty=False), t_s, SOURCE_VEHICLE)
        out = map_to_base(tracker.tracks(t_s), est, pose_uncertainty=False)
        errors.append(out.xy[0] - truth_b)
        covs.append(out.cov_xy[0])
    return _nees(errors, covs)


def test_monte_carlo_own_tracks_follow_the_drifting_ego_map():
    """The estimate's error moves between cycles; a tracker that smooths own detections in
    map' lags it. EgoMapTracker's frame noise J_m D(dt) J_m^T makes the stated covariance honest."""
    plain = _track_nees(Tracker, runs=200, cycles=20, range_m=90.0)
    drifting = _track_nees(EgoMapTracker, runs=200, cycles=20, range_m=90.0)
    assert plain > 3.5  # 5.7 here (6.2 over 500 runs, 23 at 200 m)
    assert 1.5 < drifting < 2.5  # 1.7 here (1.9 over 500 runs at 30, 90 and 200 m)


def test_ego_map_tracker_adds_the_frame_drift_over_each_prediction():
    u = PoseUncertainty(SIGMA, 5.0)
    ego = Pose2D(3.0, 4.0, 0.2, uncertainty=u)
    det = points([[103.0, 4.0], [3.0, 54.0]], np.eye(2) * 0.01)  # still, 100 m east and 50 m north of the ego
    plain, drifting = Tracker(TrackerConfig(confirm_hits=1)), EgoMapTracker(TrackerConfig(confirm_hits=1))
    drifting.ego = ego
    for tracker in (plain, drifting):
        tracker.update(det, 0.0, SOURCE_VEHICLE)
        tracker.predict(0.2)
    added = drifting.tracks(0.2).cov_xy - plain.tracks(0.2).cov_xy
    d = u.drift_cov(0.2)
    np.testing.assert_allclose(added, pose_cov_map(det.xy, ego, d), atol=1e-15)
    np.testing.assert_allclose(added[0], np.diag([d[0, 0], d[1, 1] + 100**2 * d[2, 2]]), atol=1e-15)  # yaw: north
    drifting.ego = Pose2D(3.0, 4.0, 0.2)  # an exact pose: a plain Tracker
    plain.predict(0.3)
    drifting.predict(0.3)
    np.testing.assert_allclose(drifting.tracks(0.3).cov_xy - plain.tracks(0.3).cov_xy, added, atol=1e-12)


def test_fusion_methods_add_the_pose_term_to_rsu_objects_only():
    u = PoseUncertainty(SIGMA, 5.0)
    ego = Pose2D(10.0, 0.0, np.pi / 2, uncertainty=u)  # facing north
    c_m = np.diag([0.3, 0.2])
    rsu = points([[10.0, 250.0]], c_m, src=SOURCE_RSU)  # 250 m ahead: lateral = map x
    rot = rotation(ego.yaw)
    want = rot.T @ (c_m + pose_cov_map(rsu.xy, ego, SIGMA)[0]) @ rot
    assert want[1, 1] == pytest.approx(0.3 + 0.05**2 + (250 * 0.005) ** 2)
    frame = lambda k: RsuFrame(0, k, k * 100_000_000, k * 100_000_000, rsu)  # noqa: E731
    stateless = make_fusion("rsu-only", "none").fuse(0, ego, points(np.zeros((0, 2)), np.eye(2)), [frame(0)], [])
    np.testing.assert_allclose(stateless.cov_xy[0], want, atol=1e-12)
    kf = make_fusion("kf", "none")
    own = points([[60.0, 0.0]], np.eye(2) * 0.01)  # base_link, 60 m ahead
    for k in range(3):
        out = kf.fuse(k * 100_000_000, ego, own, [frame(k)], [frame(k)])
    far = out.take(np.argmax(out.xy[:, 0]))
    np.testing.assert_allclose(far.cov_xy[0], want, atol=1e-9)  # an RSU-only track holds the newest estimate
    near = out.take(np.argmin(out.xy[:, 0]))
    assert near.cov_xy[0, 1, 1] < 0.02  # own track: no (60 m * 0.005)^2 = 0.09 lever arm
