"""The tracker's compiled estimate rules equal the numpy expressions they replaced, bit for bit, and its CI of
object lists its numpy reference, to rounding."""

import numpy as np
import pytest

from v2i.fusion.covariance_intersection import ci_fuse_objects, ci_fuse_objects_reference
from v2i.fusion.track_table import (_mask_columns, estimate_rules, estimate_rules_reference, mask_columns_reference,
                                record_matches, record_matches_reference)
from schemas.messages import UNKNOWN_VELOCITY_VAR


@pytest.mark.parametrize("seed", range(40))
def test_estimate_rules_group_the_pairs_as_the_numpy_expressions(seed):
    rng = np.random.default_rng(seed)
    n_tracks, n_dets, n_bits = int(rng.integers(1, 12)), int(rng.integers(1, 12)), int(rng.integers(1, 6))
    t_s, max_coast_s = 10.0, 0.6
    seen_s = np.where(rng.random((n_tracks, n_bits)) < 0.3, -np.inf, t_s - rng.choice([0.0, 0.3, 0.6, 0.7, 2.0],
                                                                                      (n_tracks, n_bits)))
    cols = rng.random((n_dets, n_bits)) < 0.3
    col_values = np.int64(1) << rng.permutation(8)[:n_bits].astype(np.int64)
    k = int(rng.integers(0, min(n_tracks, n_dets) + 1))
    ti, di = rng.permutation(n_tracks)[:k].astype(np.int64), rng.permutation(n_dets)[:k].astype(np.int64)
    for mask in (int(rng.integers(0, 256)), -1, 0):
        order, n_alone, n_ci = estimate_rules(seen_s, ti, cols, di, col_values, mask, t_s, max_coast_s)
        want = estimate_rules_reference(seen_s, ti, cols, di, col_values, mask, t_s, max_coast_s)
        assert order.tolist() == want[0].tolist() and (n_alone, n_ci) == want[1:]


def _spd(rng, k, d, scale):
    a = rng.normal(size=(k, d, d)) * scale
    return a @ a.transpose(0, 2, 1) + 1e-3 * np.eye(d)


@pytest.mark.parametrize("seed", range(60))
def test_ci_fuse_objects_equals_its_numpy_reference(seed):
    """The compiled CI of an object list equals ci_fuse_objects_reference (the grouped numpy ci_weights and
    ci_update_into) to rounding: position-only and position-velocity pairs, broken covariances (w = 1, no update),
    states of 4 and 6 entries; the rows not named stay as they were, bit for bit."""
    rng = np.random.default_rng(seed)
    n_tracks, n_dets, dim = int(rng.integers(1, 10)), int(rng.integers(1, 10)), int(rng.choice([4, 6]))
    x, p = rng.normal(0, 20, (n_tracks, dim)), _spd(rng, n_tracks, dim, rng.choice([0.1, 1.0, 5.0]))
    xy, vxy = rng.normal(0, 20, (n_dets, 2)), rng.normal(0, 5, (n_dets, 2))
    cov_xy, cov_vxy = _spd(rng, n_dets, 2, rng.choice([0.05, 1.0, 10.0])), _spd(rng, n_dets, 2, 0.5)
    cov_vxy[rng.random(n_dets) < 0.4] = np.eye(2) * UNKNOWN_VELOCITY_VAR  # no velocity measured
    if seed % 7 == 0:
        cov_xy[0, 0, 0] = np.nan  # a broken covariance: w = 1, no update
    k = int(rng.integers(0, min(n_tracks, n_dets) + 1))
    rows, cols = rng.permutation(n_tracks)[:k].astype(np.int64), rng.permutation(n_dets)[:k].astype(np.int64)
    others = np.setdiff1d(np.arange(n_tracks), rows)
    for velocity in (True, False):
        got_x, got_p, want_x, want_p = x.copy(), p.copy(), x.copy(), p.copy()
        ci_fuse_objects(got_x, got_p, rows, xy, cov_xy, vxy, cov_vxy, cols, velocity)
        ci_fuse_objects_reference(want_x, want_p, rows, xy, cov_xy, vxy, cov_vxy, cols, velocity)
        np.testing.assert_allclose(got_x, want_x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(got_p, want_p, rtol=1e-8, atol=1e-9)
        np.testing.assert_array_equal(got_x[others], x[others])
        np.testing.assert_array_equal(got_p[others], p[others])
        assert np.array_equal(got_x, x) == np.array_equal(want_x, x)  # both updated something, or neither


def test_record_matches_wraps_the_heading_and_takes_the_variance_as_the_tracker_did():
    """The box heading is frames.wrap_angle's and its variance the trace of cov_xy, bit for bit (the kernel
    computes both per matched pair; the tracker computed them for the whole list before)."""
    from v2i.core.frames import wrap_angle
    from v2i.fusion.track_table import record_matches

    rng = np.random.default_rng(5)
    yaws = np.concatenate([rng.normal(0, 10, 400), rng.normal(0, 1e6, 50), np.pi * np.arange(-9, 10),
                           [0.0, -0.0, np.pi, -np.pi, np.nextafter(np.pi, 0), np.nextafter(-np.pi, 0), 1e300, -1e-300,
                            np.inf, -np.inf, np.nan]])
    m = len(yaws)
    cov = _spd(rng, m, 2, rng.choice([0.1, 3.0]))
    ti = di = np.arange(m, dtype=np.int64)
    cls, z, lwh, yaw = np.zeros(m, np.int64), np.zeros(m), np.zeros((m, 3)), np.zeros(m)
    shape_var, shape_s, confidence = np.full(m, np.inf), np.zeros(m), np.zeros(m)
    hits, confirmed, updated_s, seen_s = np.zeros(m, np.int64), np.zeros(m, bool), np.zeros(m), np.zeros((m, 1))
    record_matches(cls, z, lwh, yaw, shape_var, shape_s, confidence, hits, confirmed, updated_s, seen_s, ti, di,
                   np.ones(m, np.int64), rng.normal(size=m), rng.random((m, 3)), yaws, cov, rng.random(m),
                   np.ones((m, 1), bool), 1.0, False, 2, 0.3)
    with np.errstate(invalid="ignore"):  # inf mod 2 pi is NaN
        want_yaw = wrap_angle(yaws)
    np.testing.assert_array_equal(yaw.view(np.uint64), want_yaw.view(np.uint64))
    np.testing.assert_array_equal(shape_var, cov[:, 0, 0] + cov[:, 1, 1])


@pytest.mark.parametrize("seed", range(20))
def test_mask_columns_are_the_numpy_expression(seed):
    from v2i.fusion.track_table import _mask_columns

    rng = np.random.default_rng(seed)
    masks = rng.integers(0, 1 << 12, int(rng.integers(0, 9))).astype(np.int64)
    col_values = np.int64(1) << rng.permutation(12)[:int(rng.integers(0, 12))].astype(np.int64)
    extra = int(rng.integers(0, 1 << 12))
    cols, union = _mask_columns(masks, extra, col_values)
    both = masks | extra
    assert cols.tolist() == ((both[:, None] & col_values) != 0).tolist()
    assert union == (int(np.bitwise_or.reduce(both)) if len(both) else 0)


def test_tracks_are_the_confirmed_rows_of_the_table_as_before():
    """Tracker.tracks gathers the columns it outputs; the former body took the whole table first."""
    from v2i.core.objects import ObjectArray
    from v2i.fusion.tracking import Tracker, TrackerConfig
    from v2i.fusion import kalman

    rng = np.random.default_rng(11)
    tracker = Tracker(TrackerConfig(gate="either"))
    truth = rng.uniform(-50, 50, (12, 2))
    for step in range(8):
        t_s = 0.1 * step
        n = len(truth) - step % 3
        dets = ObjectArray(ids=np.arange(n), cls=np.ones(n, np.int64), xy=truth[:n] + rng.normal(0, 0.3, (n, 2)),
                           z=np.zeros(n), lwh=np.ones((n, 3)), yaw=rng.normal(size=n), vxy=np.zeros((n, 2)),
                           cov_xy=np.tile(np.eye(2) * 0.1, (n, 1, 1)), sources=np.full(n, 1 << (step % 2), np.int64))
        tracker.update(dets, t_s, estimates=step % 2 == 1)
        for query_s in (t_s, t_s + 0.05):
            got = tracker.tracks(query_s)
            tab = tracker._table
            max_coast_s = tracker.config.max_coast_s
            tab = tab.take(tab.confirmed & (query_s - tab.updated_s <= max_coast_s))
            x, p = tab.x, tab.p
            if query_s != tracker.time_s and len(tab):
                x, p = kalman.predict(x, p, tracker.model, query_s - tracker.time_s)
            want = dict(ids=tab.ids, cls=tab.cls, xy=x[:, :2], z=tab.z, lwh=tab.lwh, yaw=tab.yaw, vxy=x[:, 2:4],
                        cov_xy=p[:, :2, :2], cov_vxy=p[:, 2:4, 2:4], confidence=tab.confidence,
                        age_s=query_s - tab.born_s,
                        sources=tab.source_masks((query_s - tab.seen_s) <= max_coast_s))
            assert len(got) > 0 or step == 0
            for name, column in want.items():
                np.testing.assert_array_equal(getattr(got, name), column, err_msg=name)


@pytest.mark.parametrize("seed", range(30))
def test_record_matches_equals_its_numpy_reference(seed):
    """Every column the bookkeeping writes, bit for bit: unknown and known classes, boxes taken by a smaller
    variance (1 % slack) or an old shape, confirmations by hits or estimates, seen columns by source."""
    rng = np.random.default_rng(seed)
    n, m, bits = int(rng.integers(1, 15)), int(rng.integers(1, 15)), int(rng.integers(1, 5))
    k = int(rng.integers(0, min(n, m) + 1))
    ti, di = rng.permutation(n)[:k].astype(np.int64), rng.permutation(m)[:k].astype(np.int64)
    tracks = [rng.integers(0, 3, n), rng.normal(size=n), rng.random((n, 3)), rng.normal(0, 4, n),
              rng.choice([0.5, 1.0, 2.0], n), rng.choice([0.0, 9.0], n), rng.random(n), rng.integers(0, 4, n),
              rng.random(n) < 0.3, rng.random(n), np.where(rng.random((n, bits)) < 0.5, -np.inf, 5.0)]
    dets = [rng.integers(0, 3, m), rng.normal(size=m), rng.random((m, 3)), rng.normal(0, 10, m),
            _spd(rng, m, 2, rng.choice([0.5, 1.0])), rng.random(m), rng.random((m, bits)) < 0.5]
    var = dets[4][:, 0, 0] + dets[4][:, 1, 1]
    tracks[4][ti] = var[di] / rng.choice([0.5, 0.995, 1.005, 1.02], k)  # around the 1 % slack
    for estimates in (False, True):
        got, want = [c.copy() for c in tracks], [c.copy() for c in tracks]
        args = (ti, di, *dets, 10.0, estimates, 3, 1.5)
        record_matches(*got, *args)
        record_matches_reference(*want, *args)
        for a, b in zip(got, want):
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes()


def test_mask_columns_equal_its_numpy_reference():
    rng = np.random.default_rng(2)
    col_values = np.int64(1) << np.array([0, 3, 5, 40], dtype=np.int64)
    for k in (0, 1, 7):
        masks = rng.integers(0, 2**45, k).astype(np.int64)
        for extra in (0, 8, 2**40):
            cols, union = _mask_columns(masks, extra, col_values)
            want_cols, want_union = mask_columns_reference(masks, extra, col_values)
            assert np.array_equal(cols, want_cols) and union == want_union
