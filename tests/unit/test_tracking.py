import numpy as np
import pytest

from v2i.fusion.association import assign, center_distance_cost
from v2i.fusion.geometry import bev_iou_matrix
from v2i.core.objects import ObjectArray
from v2i.fusion.oosm import OosmTracker
from v2i.fusion.tracking import Tracker, TrackerConfig, assign_gated, association_cost, compatible_classes


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


def test_compatible_classes_is_equal_or_either_unknown_for_every_class_code():
    """The product form (either is 0 exactly when the product is) against the rule as written."""
    codes = np.arange(256, dtype=np.int64)
    a, b = codes[:, None], codes[None, :]
    assert np.array_equal(compatible_classes(a, b), (a == b) | (a == 0) | (b == 0))
    assert np.array_equal(compatible_classes(codes, codes[::-1]), (codes == codes[::-1]) | (codes == 0) | (codes[::-1] == 0))


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


# --- split API, gating, cost, life cycle, classes, sources, motion models -------------------------

LIDAR, RSU = 1, 2


def confirmed_tracker(xy=(0.0, 0.0), **cfg):
    tracker = Tracker(TrackerConfig(**cfg))
    for t in (0.0, 0.1, 0.2):
        tracker.predict(t)
        tracker.update(dets(xy, std=0.2), t, LIDAR)
        tracker.prune(t)
    return tracker


def test_two_updates_per_cycle_fuse_lidar_then_rsu():
    tracker = confirmed_tracker()
    tracker.predict(0.3)
    tracker.update(dets([0.1, 0.0], std=0.2), 0.3, LIDAR)
    var_lidar = tracker.tracks(0.3).cov_xy[0, 0, 0]
    tracker.update(dets([[0.0, 0.1], [40.0, 0.0]], std=0.5), 0.3, RSU)  # the target, and one only the RSU sees
    tracker.prune(0.3)
    assert len(tracker) == 2
    out = tracker.tracks(0.3)
    assert len(out) == 1 and out.sources[0] == LIDAR | RSU
    assert out.cov_xy[0, 0, 0] < var_lidar  # the second update adds information
    tracker.predict(0.4)
    tracker.update(dets([40.0, 0.0]), 0.4, RSU)
    assert {int(s) for s in tracker.tracks(0.4).sources} == {LIDAR | RSU, RSU}


def with_velocity(d, vxy, std):
    return d.with_(vxy=np.tile(vxy, (len(d), 1)), cov_vxy=np.tile(np.eye(2) * std**2, (len(d), 1, 1)))


def test_rsu_estimate_replaces_an_rsu_only_track_and_fuses_into_a_lidar_track():
    tracker = Tracker(TrackerConfig())
    for t in (0.0, 0.1, 0.2):  # the LiDAR's track at the origin; one only the RSU sees, 40 m east
        tracker.update(dets([0.0, 0.0], std=0.2), t, LIDAR)
        tracker.update(with_velocity(dets([40.0 + 10 * t, 0.0], std=0.5), [10.0, 0.0], 0.5), t, RSU, estimates=True)
        tracker.prune(t)
    tracker.update(dets([0.0, 0.0], std=0.2), 0.3, LIDAR)
    before = tracker.tracks(0.3)
    estimate = with_velocity(dets([[0.6, 0.0], [43.4, 0.3]], std=0.4), [9.0, 0.5], 0.3)
    estimate = estimate.with_(vxy=np.array([[0.0, 0.0], [9.0, 0.5]]))
    tracker.update(estimate, 0.3, RSU, estimates=True)
    after = tracker.tracks(0.3)
    lidar, rsu_only = np.argmin(after.xy[:, 0]), np.argmax(after.xy[:, 0])
    # the RSU-only track is the newest estimate, state and covariance, not a blend with the old one
    np.testing.assert_allclose(after.xy[rsu_only], [43.4, 0.3], atol=1e-12)
    np.testing.assert_allclose(after.vxy[rsu_only], [9.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(after.cov_xy[rsu_only], np.eye(2) * 0.16, atol=1e-12)
    np.testing.assert_allclose(after.cov_vxy[rsu_only], np.eye(2) * 0.09, atol=1e-12)
    # the LiDAR's track is Kalman-updated: it moves toward the estimate, but not onto it
    x_before = before.xy[np.argmin(before.xy[:, 0]), 0]
    assert x_before < after.xy[lidar, 0] < 0.6 - 0.3
    assert after.cov_xy[lidar, 0, 0] < before.cov_xy[np.argmin(before.xy[:, 0]), 0, 0]
    assert after.sources[lidar] == LIDAR | RSU and after.sources[rsu_only] == RSU


def test_an_estimate_fused_into_a_shared_track_gives_its_position_not_its_velocity():
    """A LiDAR track, then an RSU estimate of it with a precise, different velocity: the track
    takes a filterpy position update only (the estimate's velocity is correlated over lists)."""
    from filterpy.kalman import KalmanFilter

    tracker = Tracker(TrackerConfig())
    for t in (0.0, 0.1, 0.2):
        tracker.update(with_velocity(dets([2.0 * t, 0.0], std=0.2), [2.0, 0.0], 0.3), t, LIDAR)
    tracker.predict(0.3)
    x, p = tracker._table.x[0].copy(), tracker._table.p[0].copy()
    estimate = with_velocity(dets([0.7, 0.1], std=0.4), [9.0, 1.0], 0.05)
    tracker.update(estimate, 0.3, RSU, estimates=True)
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.x, kf.P, kf.H = x[:, None], p, np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
    kf.update(np.array([0.7, 0.1]), R=estimate.cov_xy[0])
    np.testing.assert_allclose(tracker._table.x[0], kf.x[:, 0], atol=1e-12)
    np.testing.assert_allclose(tracker._table.p[0], kf.P, atol=1e-12)
    assert tracker.tracks(0.3).vxy[0, 0] < 4.0  # the 9 m/s estimate would have pulled it near 9


def test_measured_velocity_updates_the_track_and_an_unknown_one_does_not():
    def track_after(d):
        tracker = confirmed_tracker()  # at rest: velocity ~ 0
        tracker.update(d, 0.3, LIDAR)
        return tracker.tracks(0.3)

    measured = track_after(with_velocity(dets([0.0, 0.0], std=0.2), [5.0, 0.0], 0.3))
    unknown = track_after(dets([0.0, 0.0], std=0.2).with_(vxy=np.array([[5.0, 0.0]])))  # no cov_vxy stated
    assert measured.vxy[0, 0] > 4.0 and measured.cov_vxy[0, 0, 0] < 0.3**2
    assert abs(unknown.vxy[0, 0]) < 0.5

    def spawned_moving(**cfg):  # a detection says 5 m/s, but the positions never move
        tracker = Tracker(TrackerConfig(**cfg))
        for t in (0.0, 0.1, 0.2, 0.3):
            tracker.update(with_velocity(dets([0.0, 0.0], std=0.2), [5.0, 0.0], 0.3), t, LIDAR)
        return tracker.tracks(0.3).vxy[0, 0]

    assert spawned_moving() > 4.5 > spawned_moving(velocity_updates=False) + 0.5  # off: only the spawn took it


# --- track start: two-point velocity, RSU estimates confirmed on their first list -------------------


def test_second_position_initialises_the_velocity_from_two_points():
    """Born at z1 without a velocity, second position z2 dt later: v = (z2 - z1) / dt and
    P_vv = (R1 + R2) / dt^2 + sigma_a^2 dt^2 / 4, not a Kalman update against the 0 m/s prior."""
    def second_hit(**cfg):
        tracker = Tracker(TrackerConfig(confirm_hits=2, **cfg))
        tracker.update(dets([-80.0, -1.0], std=1.3), 0.0, RSU)
        tracker.update(dets([-77.0, -1.6], std=1.4), 0.2, RSU)
        return tracker.tracks(0.2)

    out = second_hit()
    np.testing.assert_allclose(out.xy[0], [-77.0, -1.6], atol=1e-12)
    np.testing.assert_allclose(out.vxy[0], [15.0, -3.0], atol=1e-9)
    np.testing.assert_allclose(out.cov_vxy[0], np.eye(2) * ((1.3**2 + 1.4**2) / 0.04 + 9.0 * 0.04 / 4), atol=1e-9)
    shrunk = second_hit(two_point_init=False).vxy[0, 0]
    assert 0 < shrunk < 0.6 * 15.0  # the old start: a 15 m/s car at less than 9 m/s


def test_two_point_only_for_tracks_and_detections_without_a_measured_velocity():
    def second_hit(first, second):
        tracker = Tracker(TrackerConfig())
        tracker.update(first, 0.0, LIDAR)
        tracker.update(second, 0.2, LIDAR)
        return tracker.tracks(0.2).vxy[0, 0]

    plain, moving = dets([0.0, 0.0]), with_velocity(dets([0.0, 0.0]), [2.0, 0.0], 0.3)
    assert second_hit(plain, dets([3.0, 0.0])) == pytest.approx(15.0)
    # a measured velocity at either hit is fused by the Kalman filter instead
    assert 1.5 < second_hit(moving, dets([3.0, 0.0])) < 3.0
    assert 1.5 < second_hit(plain, with_velocity(dets([3.0, 0.0]), [2.0, 0.0], 0.3)) < 3.0


def far_fast_car_tracks(seed, **cfg):
    """A car at 30 m/s, 150 m out, seen at 10 Hz with 1 m noise (the highway RSU camera): the ids
    of the confirmed tracks over 1.5 s, and the last output."""
    rng = np.random.default_rng(seed)
    tracker, ids, out = Tracker(TrackerConfig(**cfg)), set(), None
    for k in range(15):
        t = 0.1 * k
        out = tracker.step(dets(np.array([150.0 + 30.0 * t, 0.0]) + rng.normal(0, 1.0, 2), std=1.0), t)
        ids |= set(out.ids.tolist())
    return ids, out


@pytest.mark.parametrize("gate", ["distance", "mahalanobis", "either"])
def test_far_fast_car_converges_without_a_second_track(gate):
    seeds = range(40)
    split_new = sum(len(far_fast_car_tracks(s, gate=gate)[0]) > 1 for s in seeds)
    split_old = sum(len(far_fast_car_tracks(s, gate=gate, two_point_init=False)[0]) > 1 for s in seeds)
    assert split_new <= 4 and split_old >= 2 * split_new, (split_new, split_old)
    ids, out = far_fast_car_tracks(0, gate=gate)
    assert len(ids) == 1 and out.vxy[0, 0] == pytest.approx(30.0, abs=3.0)


def rsu_estimate(xy, vxy=(10.0, 0.0)):
    return with_velocity(dets(xy, std=0.8), vxy, 1.0)


def test_rsu_estimate_is_confirmed_on_its_first_list():
    tracker = Tracker(TrackerConfig())
    tracker.update(rsu_estimate([40.0, 0.0]), 0.0, RSU, estimates=True)
    out = tracker.tracks(0.0)
    assert len(out) == 1 and out.sources[0] == RSU and tracker.lifecycle(0.0) == {1: "confirmed"}
    plain = Tracker(TrackerConfig())
    plain.update(rsu_estimate([40.0, 0.0]), 0.0, RSU)  # a detection, not another tracker's track
    assert len(plain.tracks(0.0)) == 0 and plain.lifecycle(0.0) == {1: "tentative"}
    tentative = Tracker(TrackerConfig(confirm_hits=3))  # LiDAR's tentative track, matched by an estimate
    tentative.update(dets([0.0, 0.0]), 0.0, LIDAR)
    tentative.update(rsu_estimate([0.3, 0.0]), 0.0, RSU, estimates=True)
    assert tentative.lifecycle(0.0) == {1: "confirmed"}


@pytest.mark.parametrize("lists", [1, 3])
def test_rsu_only_objects_are_deleted_when_they_were_before(lists):
    """A ghost in `lists` RSU lists (5 Hz), then never again: as an estimate it shows from its
    first list, and is deleted at the same cycle as when it had to be confirmed by a second list
    (heard once: after tentative_max_coast_s = 0.3 s; more often: max_coast_s = 0.6 s after the last)."""
    def lifetime(estimates):
        tracker, shown, alive = Tracker(TrackerConfig()), [], []
        for k in range(20):  # 10 Hz cycles
            t = round(0.1 * k, 10)
            tracker.predict(t)
            if k % 2 == 0 and k // 2 < lists:
                tracker.update(rsu_estimate([40.0 + t, 0.0]), t, RSU, estimates)
            tracker.prune(t)
            shown.append(len(tracker.tracks(t)))
            alive.append(len(tracker))
        return shown, alive

    shown, alive = lifetime(True)
    shown_before, alive_before = lifetime(False)
    assert alive == alive_before and shown == alive  # the same life, all of it shown
    assert sum(shown_before) == (0 if lists == 1 else sum(alive) - 2)  # before: from the second list on
    last = max(k for k, n in enumerate(alive) if n)
    assert last == (3 if lists == 1 else 2 * (lists - 1) + 6)


def test_mahalanobis_gate_rejects_an_outlier_the_distance_gate_accepts():
    for gate, expected_tracks in (("distance", 1), ("mahalanobis", 2)):
        tracker = confirmed_tracker(gate=gate)
        tracker.predict(0.3)
        tracker.update(dets([3.5, 0.0], std=0.2), 0.3, LIDAR)  # 3.5 m < gate_m, d2 >> 9.21
        assert len(tracker) == expected_tracks, gate


def test_either_gate_passes_what_one_of_the_two_gates_passes():
    """A settled track 3.5 m from a precise detection (distance gate only) and a young RSU track
    whose velocity is unknown 6.2 m from the next list 0.4 s later (Mahalanobis gate only):
    ``either`` keeps both on their track, each single gate splits one of them."""
    def settled(gate):
        tracker = confirmed_tracker(gate=gate)
        tracker.predict(0.3)
        tracker.update(dets([3.5, 0.0], std=0.2), 0.3, LIDAR)
        return len(tracker)

    def young(gate):
        tracker = Tracker(TrackerConfig(gate=gate))
        tracker.update(with_velocity(dets([40.0, 0.0], std=1.4), (9.5, -3.6), 9.6), 0.0, RSU, estimates=True)
        tracker.predict(0.4)
        tracker.update(with_velocity(dets([48.6, 2.3], std=1.1), (18.8, 3.7), 3.1), 0.4, RSU, estimates=True)
        return len(tracker)

    assert (settled("distance"), settled("mahalanobis"), settled("either")) == (1, 2, 1)
    assert (young("distance"), young("mahalanobis"), young("either")) == (2, 1, 1)


def test_either_gate_stops_at_gate_max_m():
    """An estimate 20 m off with a 15 m position std (an unknown velocity moved 150 ms) passes
    the Mahalanobis gate; ``either`` does not pair anything farther than gate_max_m (15 m)."""
    def tracks(gate):
        tracker = confirmed_tracker(gate=gate)
        tracker.predict(0.3)
        tracker.update(dets([20.0, 0.0], std=15.0), 0.3, RSU, estimates=True)
        return len(tracker)

    assert (tracks("mahalanobis"), tracks("either")) == (1, 2)


def test_mahalanobis_cost_prefers_the_likely_track_over_the_nearest():
    tracker = Tracker(TrackerConfig(cost="mahalanobis", gate="mahalanobis"))
    tracker.predict(0.0)
    tracker.update(dets([[0.0, 0.0], [3.0, 0.0]]), 0.0, LIDAR)
    tracker._table.p[0, :2, :2] = np.eye(2) * 25.0  # track 1 very uncertain, track 2 sure
    tracker._table.p[1, :2, :2] = np.eye(2) * 0.01
    cost = association_cost(tracker.config, tracker._table, dets([1.8, 0.0]))
    assert assign_gated(cost).matches.tolist() == [[0, 0]]  # nearer to track 2, likelier for track 1


def test_iou_cost_is_one_minus_bev_iou_inside_the_gate():
    tracker = confirmed_tracker(cost="iou")
    d = dets([[1.0, 0.3], [30.0, 0.0]])
    cost = association_cost(tracker.config, tracker._table, d)
    box = np.column_stack([tracker._table.x[:, :2], tracker._table.lwh[:, :2], tracker._table.yaw])
    assert cost[0, 0] == pytest.approx(1.0 - bev_iou_matrix(box, np.column_stack([d.xy, d.lwh[:, :2], d.yaw]))[0, 0])
    assert np.isinf(cost[0, 1])  # outside the 5 m gate
    tracker.predict(0.3)
    tracker.update(d, 0.3, LIDAR)
    assert len(tracker) == 2 and tracker.tracks(0.3).xy[0, 0] > 0.1


def test_life_cycle_tentative_confirmed_coasting_deleted():
    cfg = TrackerConfig(confirm_hits=3, max_coast_s=0.5, tentative_max_coast_s=0.15)
    tracker = Tracker(cfg)

    def cycle(t, *xy):
        tracker.predict(t)
        tracker.update(dets(np.array(xy).reshape(-1, 2)), t, LIDAR)
        tracker.prune(t)
        return tracker.lifecycle(t)

    assert cycle(0.0, [0, 0]) == {1: "tentative"}
    assert cycle(0.1, [0, 0], [20, 0]) == {1: "tentative", 2: "tentative"}
    assert cycle(0.2, [0, 0]) == {1: "confirmed", 2: "tentative"}  # third hit; track 2 missed once
    assert cycle(0.3, [0, 0]) == {1: "confirmed"}  # track 2 missed for 0.2 s > 0.15 s
    assert cycle(0.5) == {1: "coasting"}
    assert len(tracker.tracks(0.5)) == 1
    assert cycle(0.8) == {1: "coasting"}  # 0.5 s since the last update
    assert cycle(0.81) == {}


def test_tentative_track_survives_until_the_next_frame_of_a_slow_source():
    tracker = Tracker(TrackerConfig(tentative_max_coast_s=0.25))
    for k in range(5):  # the RSU (5 Hz) sees it, the LiDAR (10 Hz) never does
        t = 0.1 * k
        tracker.predict(t)
        tracker.update(ObjectArray.empty(), t, LIDAR)
        if k % 2 == 0:
            tracker.update(dets([50.0 + 0.1 * k, 0.0]), t, RSU)
        tracker.prune(t)
    out = tracker.tracks(0.4)
    assert len(out) == 1 and out.sources[0] == RSU


def test_classes_never_mix_but_unknown_matches_anything():
    tracker = confirmed_tracker()  # class 1 (car)
    tracker.predict(0.3)
    tracker.update(dets([0.2, 0.0], cls=5), 0.3, LIDAR)  # a pedestrian on the car: new track
    assert len(tracker) == 2
    tracker.predict(0.4)
    tracker.update(dets([[0.0, 0.0]], cls=0), 0.4, RSU)  # unknown class updates the nearest track
    assert len(tracker) == 2
    unknown = Tracker(TrackerConfig(confirm_hits=2))
    unknown.step(dets([0, 0], cls=0), 0.0)
    out = unknown.step(dets([0, 0], cls=3), 0.1)
    assert len(out) == 1 and out.cls[0] == 3  # an UNKNOWN track adopts the class it is matched with


def test_sources_bitmask_forgets_sources_older_than_max_coast():
    tracker = confirmed_tracker(max_coast_s=0.3)
    for k in range(3, 10):
        t = 0.1 * k
        tracker.predict(t)
        tracker.update(dets([0.0, 0.0]), t, RSU)
        tracker.prune(t)
        expected = LIDAR | RSU if t - 0.2 <= 0.3 + 1e-9 else RSU
        assert tracker.tracks(t).sources.tolist() == [expected], t


def test_tracks_predicts_a_copy_and_time_never_goes_back():
    tracker = confirmed_tracker()
    tracker._table.x[0, 2:] = [10.0, 0.0]
    before = tracker.snapshot()
    ahead = tracker.tracks(0.7)
    assert ahead.xy[0, 0] == pytest.approx(tracker._table.x[0, 0] + 5.0)
    np.testing.assert_array_equal(tracker._table.x, before.table.x)
    with pytest.raises(ValueError, match="OosmTracker"):
        tracker.predict(0.1)
    tracker.update(dets([0, 0]), 0.3, 1 << 62)  # bits 0..62 are sources (one per RSU slot); bit 63 is not
    with pytest.raises(ValueError, match="source"):
        tracker.update(dets([0, 0]), 0.3, -(1 << 63))


def test_snapshot_restore_is_a_deep_copy():
    tracker = confirmed_tracker()
    snap = tracker.snapshot()
    expected = tracker.tracks(0.2)
    for _ in range(2):
        tracker.step(dets([[1.0, 1.0], [9.0, 9.0]]), 0.5)
        tracker.restore(snap)
        got = tracker.tracks(0.2)
        np.testing.assert_array_equal(got.xy, expected.xy)
        np.testing.assert_array_equal(got.cov_xy, expected.cov_xy)
        assert got.ids.tolist() == expected.ids.tolist() and tracker._next_id == 2


def turning_run(motion, seed=7):
    """A car on a 20 m circle at 10 m/s (0.5 rad/s), 10 Hz noisy positions; errors after 3 s."""
    rng = np.random.default_rng(seed)
    tracker = Tracker(TrackerConfig(motion=motion, accel_std_mps2=1.0, yaw_accel_std_radps2=0.3))
    now_err, ahead_err = [], []
    for k in range(100):
        t = 0.1 * k
        ang = 0.5 * t
        truth = np.array([20 * np.sin(ang), 20 - 20 * np.cos(ang)])
        d = dets(truth + rng.normal(0, 0.3, 2), std=0.3).with_(yaw=np.array([ang]))
        out = tracker.step(d, t)
        if t >= 3.0:
            ahead = 0.5 * (t + 0.5)
            now_err.append(np.linalg.norm(out.xy[0] - truth))
            ahead_err.append(np.linalg.norm(tracker.tracks(t + 0.5).xy[0] - [20 * np.sin(ahead), 20 - 20 * np.cos(ahead)]))
    return np.sqrt(np.mean(np.square(now_err))), np.sqrt(np.mean(np.square(ahead_err)))


def test_ctrv_tracks_a_turning_target_better_than_cv():
    cv_now, cv_ahead = turning_run("cv")
    ctrv_now, ctrv_ahead = turning_run("ctrv")
    ca_now, _ = turning_run("ca")
    assert ctrv_now < cv_now and ctrv_ahead < 0.5 * cv_ahead
    assert ctrv_now < 0.3 and ca_now < 0.5


def test_config_rejects_unknown_options():
    for bad in ({"motion": "bicycle"}, {"gate": "iou"}, {"cost": "euclid"}):
        with pytest.raises(ValueError):
            TrackerConfig(**bad)


# --- out-of-sequence measurements -------------------------------------------------------------------


def two_car_batches(seed=11):
    """LiDAR lists at 10 Hz (time, arrival) and RSU lists at 5 Hz arriving 0.12-0.35 s late."""
    rng = np.random.default_rng(seed)
    batches = []
    for k in range(40):
        t = round(0.1 * k, 10)
        truth = np.array([[-30 + 12 * t, -2.0], [5.0, 10 - 8 * t]])
        if k % 2 == 0:
            batches.append((t, t + rng.uniform(0.12, 0.35), dets(truth + rng.normal(0, 0.6, (2, 2)), std=0.6), RSU))
        lidar = truth[truth[:, 0] > -15] if t < 2.5 else truth  # the first car appears late for the LiDAR
        batches.append((t, t + 0.05, dets(lidar + rng.normal(0, 0.2, lidar.shape), std=0.2), LIDAR))
    return batches


def in_order(batches, cfg, estimates=False):
    tracker = Tracker(cfg)
    for t, _, d, src in sorted(batches, key=lambda b: b[0]):
        if tracker.time_s is not None and t > tracker.time_s:
            tracker.prune(tracker.time_s)
        tracker.predict(t)
        tracker.update(d, t, src, estimates and src == RSU)
    return tracker


@pytest.mark.parametrize("estimates", [False, True], ids=["measurements", "rsu-estimates"])
def test_oosm_out_of_order_equals_in_order_filtering(estimates):
    cfg = TrackerConfig(motion="ca", gate="mahalanobis", gate_chi2=16.0)
    batches = sorted(two_car_batches(), key=lambda b: b[1])  # arrival order
    oosm = OosmTracker(Tracker(cfg), window_s=0.5)
    for n, (t, arrival, d, src) in enumerate(batches, 1):
        oosm.update(d, t, src, estimates and src == RSU)
        if n % 7 == 0 or n == len(batches):
            ref = in_order(batches[:n], cfg, estimates)
            got, want = oosm.tracks(arrival), ref.tracks(arrival)
            assert got.ids.tolist() == want.ids.tolist()
            np.testing.assert_allclose(got.xy, want.xy, rtol=0, atol=1e-9)
            np.testing.assert_allclose(got.vxy, want.vxy, rtol=0, atol=1e-9)
            np.testing.assert_allclose(got.cov_xy, want.cov_xy, rtol=0, atol=1e-9)
            assert got.sources.tolist() == want.sources.tolist()
    assert oosm.refilter_runs > 0 and oosm.dropped_batches == 0
    assert len(oosm.tracks(4.0)) == 2


def test_late_measurement_corrects_the_track_and_too_late_is_dropped():
    def run(late):
        oosm = OosmTracker(Tracker(TrackerConfig(accel_std_mps2=3.0)), window_s=0.5)
        for k in range(11):  # 10 m/s east until 1.0 s, then the LiDAR loses it
            oosm.update(dets([10.0 * 0.1 * k, 0.0], std=0.2), 0.1 * k, LIDAR)
        for t in (1.1, 1.2, 1.3):
            oosm.update(ObjectArray.empty(), t, LIDAR)
        if late is not None:  # it braked: the RSU saw it at 11 m at 1.2 s, the list arrives at 1.3 s
            oosm.update(dets([11.0, 0.0], std=0.1), late, RSU)
        return oosm

    truth_x = 11.0
    blind, corrected = run(None), run(1.2)
    err_blind = abs(blind.tracks(1.2).xy[0, 0] - truth_x)
    err_corrected = abs(corrected.tracks(1.2).xy[0, 0] - truth_x)
    assert err_corrected < 0.3 * err_blind and corrected.refilter_runs == 1
    assert corrected.tracks(1.3).vxy[0, 0] < blind.tracks(1.3).vxy[0, 0] - 1.0  # and it slowed the track
    assert corrected.tracks(1.3).sources.tolist() == [LIDAR | RSU]
    dropped = run(0.7)  # older than 1.3 - 0.5 s
    assert dropped.dropped_batches == 1 and dropped.dropped_measurements == 1
    np.testing.assert_array_equal(dropped.tracks(1.3).xy, blind.tracks(1.3).xy)
