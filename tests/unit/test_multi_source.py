"""Several cooperative sources in the OBU: a source bit per RSU slot, covariance intersection of
correlated estimates, the wire's one-byte sources, and a hand-over between two RSUs."""

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from v2i.fusion.covariance_intersection import (
    W_MIN,
    ci_update,
    ci_weights,
    covariance_intersection,
)
from v2i.core.frames import Pose2D
from v2i.core.objects import ObjectArray
from v2i.fusion.tracking import SOURCE_BITS, Tracker, TrackerConfig, slot_source
from v2i.fusion.wire import states_from_objects, wire_sources
from obu_service.pipeline import ObuPipeline, ObuPipelineConfig
from obu_service.rsu_table import MAX_RSUS
from rsu_service.pipeline import answer_time_request
from schemas.messages import SOURCE_RSU, SOURCE_VEHICLE, ObjectList, ObjectListHeader

LIDAR, RSU_A, RSU_B = SOURCE_VEHICLE, slot_source(0), slot_source(1)


def spd(rng: np.random.Generator, k: int, n: int) -> np.ndarray:
    """(k, n, n) random symmetric positive definite matrices."""
    a = rng.normal(size=(k, n, n))
    return a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(n)


def test_ci_update_equals_the_information_form():
    """Kalman update with P / w and R / (1 - w) == (w P^-1 + (1 - w) H^T R^-1 H)^-1, full and partial."""
    rng = np.random.default_rng(3)
    k = 50
    x, p, w = rng.normal(size=(k, 4)), spd(rng, k, 4), rng.uniform(0.05, 0.95, k)
    z4, r4 = rng.normal(size=(k, 4)), spd(rng, k, 4)
    x_ci, p_ci = ci_update(x, p, z4, r4, w)
    x_ref, p_ref = covariance_intersection(x, p, z4, r4, w)
    np.testing.assert_allclose(x_ci, x_ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(p_ci, p_ref, rtol=1e-9, atol=1e-9)
    # partial: position of a 4-state, P2^-1 = H^T R^-1 H
    z2, r2 = rng.normal(size=(k, 2)), spd(rng, k, 2)
    x_ci, p_ci = ci_update(x, p, z2, r2, w)
    h = np.eye(4)[:2]
    info = w[:, None, None] * np.linalg.inv(p) + (1 - w)[:, None, None] * (h.T @ np.linalg.inv(r2) @ h)
    p_ref = np.linalg.inv(info)
    x_ref = (p_ref @ (w[:, None, None] * np.linalg.inv(p) @ x[:, :, None]
                      + (1 - w)[:, None, None] * h.T @ np.linalg.inv(r2) @ z2[:, :, None]))[:, :, 0]
    np.testing.assert_allclose(x_ci, x_ref, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(p_ci, p_ref, rtol=1e-8, atol=1e-9)


@pytest.mark.parametrize("m", [2, 4])
def test_ci_weight_minimises_the_determinant(m):
    rng = np.random.default_rng(m)
    k = 30
    x, p = rng.normal(size=(k, 4)), spd(rng, k, 4)
    z, r = rng.normal(size=(k, m)), spd(rng, k, m) * rng.uniform(0.1, 10, (k, 1, 1))
    w = ci_weights(p, r)

    def det_at(i, wi):
        return np.linalg.det(ci_update(x[i:i + 1], p[i:i + 1], z[i:i + 1], r[i:i + 1], np.array([wi]))[1][0])

    inside = 0
    for i in range(k):
        best = minimize_scalar(lambda wi, i=i: det_at(i, wi), bounds=(1e-6, 1 - 1e-9), method="bounded",
                               options={"xatol": 1e-10})
        assert det_at(i, w[i]) <= best.fun * (1 + 1e-7)
        grid = [det_at(i, g) for g in np.linspace(0.01, 0.99, 99)]
        assert det_at(i, w[i]) <= min(grid) * (1 + 1e-9)
        inside += 0.0 < w[i] < 1.0
    assert inside > k // 3  # the cases are not all at a bound


def test_ci_is_consistent_for_any_correlation_and_kf_is_not():
    """x = A x1 + B x2 with A + B = I: true error covariance A P1 A^T + B P2 B^T + A C B^T + B C^T A^T.
    CI's P bounds it for fully correlated errors; the Kalman update's P does not."""
    rng = np.random.default_rng(7)
    p1, p2 = spd(rng, 1, 4)[0], spd(rng, 1, 4)[0]
    c = np.linalg.cholesky(p1) @ np.linalg.cholesky(p2).T  # errors e2 = L2 L1^-1 e1: fully correlated
    w = ci_weights(p1[None], p2[None])
    _, p_ci = ci_update(np.zeros((1, 4)), p1[None], np.zeros((1, 4)), p2[None], w)
    p_kf = np.linalg.inv(np.linalg.inv(p1) + np.linalg.inv(p2))
    assert 0.0 < w[0] < 1.0
    slack = {}
    for name, p, weight in (("ci", p_ci[0], w[0]), ("kf", p_kf, 1.0)):
        a = weight * p @ np.linalg.inv(p1)  # CI: A = w P P1^-1; KF: A = P P1^-1
        b = np.eye(4) - a
        true = a @ p1 @ a.T + b @ p2 @ b.T + a @ c @ b.T + b @ c.T @ a.T
        slack[name] = np.linalg.eigvalsh(p - true).min()
    assert slack["ci"] > -1e-9 and slack["kf"] < -1e-3  # CI bounds the error, KF is over-confident


def bisection_weights(p: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The previous weight search (52 halvings of [W_MIN, 1] on g(w)), from numpy's generalised
    eigenvalues, the reference of the Newton search; valid pairs only."""
    n, m = p.shape[-1], r.shape[-1]
    s = p[:, :m, :m]
    chol = np.linalg.cholesky(r)
    half = np.linalg.solve(chol, s)
    lam = np.linalg.eigvalsh(np.linalg.solve(chol, np.swapaxes(half, -1, -2)))  # eig(R^-1 S)

    def slope(wt):  # g(w) = (n - m) / w + sum (1 - lambda) / (w (1 - lambda) + lambda)
        return (n - m) / wt + ((1 - lam) / (wt[:, None] * (1 - lam) + lam)).sum(axis=1)

    lo, hi = np.full(len(lam), W_MIN), np.ones(len(lam))
    for _ in range(52):
        mid = 0.5 * (lo + hi)
        rising = slope(mid) > 0
        lo, hi = np.where(rising, mid, lo), np.where(rising, hi, mid)
    w = 0.5 * (lo + hi)
    w[slope(np.ones(len(lam))) >= 0] = 1.0
    w[slope(np.full(len(lam), W_MIN)) <= 0] = W_MIN
    return w


@pytest.mark.parametrize("n, m", [(4, 2), (4, 4), (6, 2), (6, 4), (5, 2)])
def test_newton_weight_equals_the_bisection(n, m):
    """Scales over four decades on both sides: interior optima, w = 1 and w = W_MIN all occur."""
    rng = np.random.default_rng(10 * n + m)
    k = 400
    p = spd(rng, k, n) * 10.0 ** rng.uniform(-2, 2, (k, 1, 1))
    r = spd(rng, k, m) * 10.0 ** rng.uniform(-2, 2, (k, 1, 1))
    same = np.zeros(k, bool)
    if m == n:  # identical covariances: P+ = P for every w, whose choice is up to rounding in g
        same[:5], r[:5] = True, p[:5]
    w, ref = ci_weights(p, r), bisection_weights(p, r)
    np.testing.assert_allclose(w[~same], ref[~same], rtol=0, atol=1e-9)
    inside = (w > W_MIN) & (w < 1.0)
    assert inside.sum() > k // 4 and (w == 1.0).any()
    # the fused covariance at the Newton weight is CI's (information form) and no larger in det
    x, z = rng.normal(size=(k, n)), rng.normal(size=(k, m))
    _, p_new = ci_update(x, p, z, r, w)
    _, p_ref = ci_update(x, p, z, r, ref)
    assert np.all(np.linalg.det(p_new[inside]) <= np.linalg.det(p_ref[inside]) * (1 + 1e-9))
    np.testing.assert_allclose(p_new, p_ref, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(p_new[same], p[same], rtol=1e-6)


def test_ci_fuse_rows_is_weights_then_update_on_the_table_rows():
    """The tracker's in-place kernel on rows of a larger table equals ci_weights + ci_update on the
    gathered rows, leaves the other rows alone, and skips pairs whose weight is 1 (position, and
    position with velocity)."""
    from v2i.fusion.covariance_intersection import ci_fuse_rows

    rng = np.random.default_rng(7)
    for m in (2, 4):
        x, p = rng.normal(size=(30, 4)), spd(rng, 30, 4)
        rows = rng.choice(30, 12, replace=False)
        z, r = rng.normal(size=(12, m)), spd(rng, 12, m) * 10.0 ** rng.uniform(-2, 2, (12, 1, 1))
        w = ci_weights(p[rows], r)
        assert (w == 1.0).any() and (w < 1.0).any()
        x_ref, p_ref = ci_update(x[rows], p[rows], z, r, w)
        x_new, p_new = x.copy(), p.copy()
        ci_fuse_rows(x_new, p_new, rows, z, r)
        np.testing.assert_array_equal(x_new[rows], x_ref)
        np.testing.assert_array_equal(p_new[rows], p_ref)
        others = np.setdiff1d(np.arange(30), rows)
        np.testing.assert_array_equal(x_new[others], x[others])
        np.testing.assert_array_equal(p_new[others], p[others])


def test_ci_weights_refuse_broken_covariances_without_raising():
    p = np.tile(np.eye(4), (3, 1, 1))
    r = np.stack([np.full((2, 2), np.nan), np.array([[1.0, 2.0], [2.0, 1.0]]), np.eye(2) * 0.1])
    w = ci_weights(p, r)
    assert w[0] == 1.0 and w[1] == 1.0 and w[2] < 1.0


def dets(xy, std, vxy=None, vstd=None, sources=0):
    xy = np.atleast_2d(np.asarray(xy, float))
    n = len(xy)
    out = ObjectArray(ids=np.full(n, -1), cls=np.ones(n, int), xy=xy, z=np.zeros(n),
                      lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=np.zeros(n), vxy=np.zeros((n, 2)),
                      cov_xy=np.tile(np.eye(2) * std**2, (n, 1, 1)), sources=np.full(n, sources, np.int64))
    if vxy is not None:
        out = out.with_(vxy=np.tile(vxy, (n, 1)), cov_vxy=np.tile(np.eye(2) * vstd**2, (n, 1, 1)))
    return out


def test_a_second_rsu_intersects_instead_of_replacing_and_one_rsu_alone_still_replaces():
    tracker = Tracker(TrackerConfig())
    for t in (0.0, 0.1, 0.2):
        tracker.update(dets([10.0 * t, 0.0], 0.5, [10.0, 0.0], 0.5), t, RSU_A, estimates=True)
    tracker.predict(0.3)
    x, p = tracker._table.x.copy(), tracker._table.p.copy()
    est_b = dets([3.6, 0.4], 0.6, [9.0, 0.5], 0.45)
    tracker.update(est_b, 0.3, RSU_B, estimates=True)
    z = np.array([[3.6, 0.4, 9.0, 0.5]])
    r = np.diag([0.36, 0.36, 0.2025, 0.2025])[None]
    w = ci_weights(p, r)
    x_ref, p_ref = ci_update(x, p, z, r, w)
    assert 0.0 < w[0] < 1.0
    np.testing.assert_allclose(tracker._table.x, x_ref, atol=1e-12)
    np.testing.assert_allclose(tracker._table.p, p_ref, atol=1e-12)
    assert not np.allclose(tracker._table.x[0], z[0])  # B did not replace A's state
    assert tracker.tracks(0.3).sources.tolist() == [RSU_A | RSU_B]
    assert wire_sources(tracker.tracks(0.3).sources).tolist() == [SOURCE_RSU]
    # RSU A again: B updated the track, so A's estimate intersects too (no replace)
    tracker.update(dets([4.7, 0.0], 0.5, [10.0, 0.0], 0.5), 0.4, RSU_A, estimates=True)
    assert not np.allclose(tracker._table.x[0, :2], [4.7, 0.0])
    # once B is silent for max_coast_s, A alone replaces again
    tracker.update(dets([12.0, 0.0], 0.5, [10.0, 0.0], 0.5), 1.1, RSU_A, estimates=True)
    np.testing.assert_allclose(tracker._table.x[0], [12.0, 0.0, 10.0, 0.0])


def test_estimate_fusion_kf_and_lidar_only_tracks_keep_the_kalman_position_update():
    """A LiDAR + one RSU track is Kalman-updated (single-RSU behaviour unchanged), as is every
    shared track with estimate_fusion="kf"."""
    for config, src_b in ((TrackerConfig(), LIDAR), (TrackerConfig(estimate_fusion="kf"), RSU_B)):
        tracker = Tracker(config)
        tracker.update(dets([0.0, 0.0], 0.3), 0.0, src_b, estimates=src_b != LIDAR)
        tracker.update(dets([0.0, 0.0], 0.3), 0.1, src_b, estimates=src_b != LIDAR)
        tracker.predict(0.2)
        x, p = tracker._table.x.copy(), tracker._table.p.copy()
        tracker.update(dets([0.5, 0.0], 0.5, [3.0, 0.0], 0.1), 0.2, RSU_A, estimates=True)
        s = p[0, :2, :2] + np.eye(2) * 0.25
        gain = p[0, :, :2] @ np.linalg.inv(s)
        np.testing.assert_allclose(tracker._table.x[0], x[0] + gain @ (np.array([0.5, 0.0]) - x[0, :2]), atol=1e-12)


def test_source_bits_and_the_wire_byte():
    assert [slot_source(i) for i in (0, 1, 61)] == [SOURCE_RSU, 4, 1 << 62]
    with pytest.raises(ValueError):
        slot_source(SOURCE_BITS - 1)
    masks = np.array([1, 2, 4, 1 << 62, 1 | 8, 0])
    assert wire_sources(masks).tolist() == [1, 2, 2, 2, 3, 0]
    objs = dets([[0.0, 0.0], [5.0, 0.0]], 0.5).with_(ids=np.array([1, 2]), sources=np.array([1 | (1 << 40), 1 << 9]))
    assert [o.sources for o in states_from_objects(objs, fused=True)] == [SOURCE_VEHICLE | SOURCE_RSU, SOURCE_RSU]


def test_rsu_slots_are_capped_at_the_source_bits():
    assert MAX_RSUS == SOURCE_BITS - 1 == 62
    ObuPipelineConfig(known_rsus={f"r{i}": (0.0, 0.0) for i in range(46)}, max_unknown_rsus=16)
    with pytest.raises(ValueError, match="exceed 62 RSU slots"):
        ObuPipelineConfig(known_rsus={f"r{i}": (0.0, 0.0) for i in range(47)}, max_unknown_rsus=16)


T0 = 1_767_225_600 * 10**9
MS = 1_000_000


def rsu_list(rsu_id: str, seq: int, capture_ns: int, xy, vxy, obj_id: int) -> ObjectList:
    est = dets([xy], 0.7, vxy, 0.5).with_(ids=np.array([obj_id]))
    header = ObjectListHeader(rsu_id=rsu_id, seq=seq, capture_time_ns=capture_ns, publish_time_ns=capture_ns + 50 * MS)
    return ObjectList(header=header, objects=states_from_objects(est))


def test_hand_over_between_two_rsus_keeps_the_obu_track_id():
    """A target crosses from RSU A's view into RSU B's: A (its id 7) sees it for 0-3 s, B (its
    id 41, 0.8 m off A's estimate) from 2 s to 5 s. The OBU publishes one id throughout."""
    p = ObuPipeline(ObuPipelineConfig(fusion="kf"))
    for rsu_id in ("rsu-a", "rsu-b"):  # clocks equal; one exchange each
        req = p.make_time_request(T0)
        p.on_time_reply(answer_time_request(req, rsu_id, T0 + 5 * MS, T0 + 5 * MS), T0 + 10 * MS)
    rng = np.random.default_rng(5)
    ids, sources = [], set()
    for k in range(50):
        t_ns = T0 + 1_000 * MS + k * 100 * MS
        truth = np.array([-60.0 + 12.0 * k * 0.1, 40.0])
        p.on_pose(t_ns, Pose2D(0.0, 0.0, 0.0))
        if k < 30:
            p.on_rsu_message(rsu_list("rsu-a", k, t_ns - 60 * MS, truth - [0.72, 0] + rng.normal(0, 0.3, 2),
                                      [12.0, 0.0], 7), t_ns - 10 * MS)
        if k >= 20:
            p.on_rsu_message(rsu_list("rsu-b", k, t_ns - 60 * MS, truth - [0.72, -0.8] + rng.normal(0, 0.3, 2),
                                      [12.0, 0.0], 41), t_ns - 5 * MS)
        p.on_detections(ObjectArray.empty(), t_ns)
        out = p.fuse(t_ns + 20 * MS)
        assert len(out.objects) <= 1
        if k >= 1:
            assert len(out.objects) == 1, k
            obj = out.objects[0]
            assert np.hypot(obj.x - truth[0], obj.y - truth[1]) < 2.0  # ego at the origin facing east
            ids.append(obj.id)
            sources.add(obj.sources)
    assert len(set(ids)) == 1 and len(ids) == 49
    assert sources == {SOURCE_RSU}


def test_ci_all_intersects_an_estimate_into_a_lidar_track_too():
    tracker = Tracker(TrackerConfig(estimate_fusion="ci-all"))
    tracker.update(dets([0.0, 0.0], 0.3), 0.0, LIDAR)
    tracker.update(dets([0.0, 0.0], 0.3), 0.1, LIDAR)
    tracker.predict(0.2)
    x, p = tracker._table.x.copy(), tracker._table.p.copy()
    tracker.update(dets([0.5, 0.0], 0.2), 0.2, RSU_A, estimates=True)
    r = np.eye(2)[None] * 0.04
    w = ci_weights(p, r)
    assert 0.0 < w[0] < 1.0
    np.testing.assert_allclose(tracker._table.x, ci_update(x, p, np.array([[0.5, 0.0]]), r, w)[0], atol=1e-12)
    with pytest.raises(ValueError, match="estimate_fusion"):
        TrackerConfig(estimate_fusion="average")
