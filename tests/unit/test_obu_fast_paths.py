"""The OBU pipeline's fast paths equal the plain expressions they replace (bit for bit)."""

import math
from collections import Counter

import numpy as np
import pytest

from v2i.core.frames import Pose2D, PoseUncertainty, wrap_angle
from v2i.fusion.pose_history import PoseHistory, _interpolate, _wrap
from v2i.clock.clock_sync import ClockSync, SyncSample
from obu_service.link_monitor import LinkMonitor, gap_loss

MS = 1_000_000


def test_scalar_wrap_equals_the_numpy_wrap_bit_for_bit():
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.uniform(-50.0, 50.0, 100_000), rng.normal(0.0, 1e-9, 1000),
                             np.array([0.0, -0.0, math.pi, -math.pi, 2 * math.pi, -2 * math.pi, 3 * math.pi,
                                       np.nextafter(math.pi, 0.0), np.nextafter(-math.pi, 0.0), 1e300, -1e-300])])
    want = wrap_angle(values)
    got = np.array([_wrap(float(v)) for v in values])
    assert np.array_equal(got.view(np.int64), want.view(np.int64))  # the same bits (signed zeros too)


def _old_interpolated_yaw(p, q, a):
    """pose_history's yaw before the scalar wrap: numpy's wrap_angle on 0-d arrays."""
    return float(wrap_angle(p.yaw + a * float(wrap_angle(q.yaw - p.yaw))))


def test_interpolated_pose_equals_the_numpy_expressions():
    rng = np.random.default_rng(1)
    u = PoseUncertainty.from_stds(0.05, 0.08, 0.005, 5.0)
    v = PoseUncertainty.from_stds(0.07, 0.02, 0.002, 2.0)
    for _ in range(2000):
        p = Pose2D(*rng.normal(0, 100, 2), float(rng.uniform(-4, 4)), uncertainty=u)
        q = Pose2D(*rng.normal(0, 100, 2), np.float64(rng.uniform(-4, 4)), uncertainty=v)
        a = float(rng.uniform(0, 1))
        got = _interpolate(p, q, a)
        assert got.yaw == _old_interpolated_yaw(p, q, a) and type(got.yaw) is float
        want_cov = (1 - a) * u.cov + a * v.cov
        assert np.array_equal(got.uncertainty.cov, want_cov) and not got.uncertainty.cov.flags.writeable
        assert got.uncertainty.correlation_time_s == (1 - a) * 5.0 + a * 2.0


def test_pose_history_uncertainty_is_a_valid_read_only_blend():
    h = PoseHistory()
    u = PoseUncertainty.from_stds(0.05, 0.08, 0.005, 5.0)
    h.add(0, Pose2D(0.0, 0.0, 0.0, uncertainty=u))
    h.add(100 * MS, Pose2D(1.0, 0.0, 0.1, uncertainty=u))
    blend = h.at(25 * MS).uncertainty
    assert isinstance(blend, PoseUncertainty) and blend.cov.shape == (3, 3)
    with pytest.raises(ValueError):
        blend.cov[0, 0] = 1.0


def _exchanges(n, seed=2, t0=10**18):
    rng = np.random.default_rng(seed)
    for k in range(n):
        t1 = t0 + k * 100 * MS
        t2 = t1 + int(rng.exponential(2e6)) + 1_000_000 + 5_000_000
        t3 = t2 + 50_000
        yield SyncSample(t1, t2, t3, t3 - 5_000_000 + int(rng.exponential(2e6)) + 1_000_000)


def _fresh_estimate(sync: ClockSync, t_ns: int):
    sync._last_estimate = None  # the estimate computed from the fit, not the kept one
    return sync.estimate_at(t_ns)


def test_kept_estimate_equals_a_fresh_one_through_adds_and_steps():
    sync = ClockSync(refit_every=3)
    samples = list(_exchanges(400))
    step = 40 * MS  # the RSU clock steps after 250 exchanges: suspects, then a new segment
    samples = samples[:250] + [SyncSample(s.t1_ns, s.t2_ns + step, s.t3_ns + step, s.t4_ns) for s in samples[250:]]
    for k, sample in enumerate(samples):
        sync.add(sample)
        for t in (sample.t4_ns, sample.t4_ns + 30 * MS, sample.t4_ns):
            kept = sync.estimate_at(t)
            assert kept == _fresh_estimate(sync, t)
            assert sync.estimate_at(t) == kept
    assert sync.steps_detected == 1


def _old_loss(mon: LinkMonitor) -> tuple[int, int]:
    """LinkMonitor.loss before its kept sequence numbers: gap_loss over the window's arrivals."""
    return gap_loss([a.seq for a in mon._arrivals], [a.epoch for a in mon._arrivals])


def _old_arrival_probability(mon: LinkMonitor, within_ms: float) -> float:
    """LinkMonitor.arrival_probability before its kept statistics."""
    latencies = [a.latency_ms for a in mon._arrivals if a.latency_ms is not None]
    if not latencies:
        return 0.0
    lost, expected = _old_loss(mon)
    on_time = float(sum(latency <= within_ms for latency in latencies)) / len(latencies)
    return (1.0 - ((lost / expected if expected else None) or 0.0)) * on_time


def test_arrival_probability_equals_the_counting_expression_as_the_window_moves():
    rng = np.random.default_rng(4)
    mon = LinkMonitor(window_ns=2_000 * MS)
    t_ns = 10**18
    for seq in range(400):
        t_ns += 100 * MS
        if rng.random() < 0.1:
            continue  # lost
        capture = t_ns - int(rng.uniform(50, 400)) * MS // 10 * 10  # ties between latencies too
        mon.on_message(seq, None if rng.random() < 0.05 else capture, None, t_ns)
        latencies = [a.latency_ms for a in mon._arrivals if a.latency_ms is not None]
        for w in [0.0, 100.0, 250.0, 1e9, *latencies[:3], float(rng.uniform(0, 500))]:
            assert mon.arrival_probability(w) == _old_arrival_probability(mon, w)
        if seq % 50 == 0:
            mon.expire(t_ns + 1_500 * MS)  # most of the window leaves at once
            assert mon.arrival_probability(200.0) == _old_arrival_probability(mon, 200.0)
        assert mon.loss() == _old_loss(mon)


def test_kept_loss_equals_gap_loss_through_restarts_reordering_duplicates_and_drops():
    rng = np.random.default_rng(5)
    mon = LinkMonitor(window_ns=3_000 * MS, max_records=20, max_misorder=10, max_dropout=50)
    t_ns, seq = 10**18, 0
    for _ in range(3000):
        t_ns += int(rng.integers(1, 150)) * MS
        r = rng.random()
        seq = (0 if r < 0.01 else seq + 200 if r < 0.02 else seq - int(rng.integers(1, 15)) if r < 0.15
               else seq + int(rng.integers(1, 4)))  # restarts, jumps, late (or duplicate) arrivals, gaps
        mon.on_message(seq, t_ns - 80 * MS if rng.random() < 0.9 else None, None, t_ns)
        assert mon.loss() == _old_loss(mon)
        w = float(rng.choice([80.0, 79.9, 200.0]))  # every latency 80 ms: all, none
        assert mon.arrival_probability(w) == _old_arrival_probability(mon, w)
    assert mon.restarts_total > 5 and mon.duplicates_total > 5 and mon.reordered_total > 5


def test_a_pose_without_its_uncertainty_is_the_same_pose():
    h = PoseHistory()
    u = PoseUncertainty.from_stds(0.05, 0.08, 0.005, 5.0)
    for k in range(20):
        h.add(k * 100 * MS, Pose2D(k * 1.5, -k * 0.5, 3.0 - 0.4 * k, 15.0, -5.0, uncertainty=u))
    for t in (-50 * MS, 0, 1234 * MS, 1900 * MS, 2500 * MS):
        with_u, without = h.at(t), h.at(t, uncertainty=False)
        assert without == with_u and with_u.uncertainty is not None  # (x, y, yaw, vx, vy) compared
    assert h.at(1234 * MS, uncertainty=False).uncertainty is None


def test_covariance_columns_written_by_slices_equal_the_gathered_ones():
    from v2i.fusion.wire import _put_cov

    rng = np.random.default_rng(6)
    cov = rng.normal(size=(7, 2, 2))
    cov[0, 1, 0], cov[1, 0, 1] = np.nan, -np.inf
    got = np.zeros((7, 6))
    _put_cov(got, 1, cov, 5)
    want = np.zeros((7, 6))
    want[:, [1, 2, 3, 5]] = cov.reshape(7, 4)[:, [0, 1, 3, 2]]  # the gather it replaces
    assert np.array_equal(got, want, equal_nan=True)


def _finite_hostile(rng, n):
    """n objects, every value finite and every position on the wire, many values beyond its other ranges."""
    def col(*shape, scale):
        a = rng.normal(0.0, scale, (n, *shape)) * np.where(rng.random((n, *shape)) < 0.2, 1e4, 1.0)
        a[rng.random(a.shape) < 0.05] = -0.0
        return a

    from v2i.core.objects import ObjectArray

    return ObjectArray(
        ids=rng.integers(-2**40, 2**40, n), cls=rng.integers(0, 5, n), xy=rng.uniform(-5000.0, 5000.0, (n, 2)),
        z=col(scale=1.0), lwh=col(3, scale=3.0), yaw=col(scale=10.0), vxy=col(2, scale=20.0),
        axy=col(2, scale=3.0), yaw_rate=col(scale=0.5), cov_xy=col(2, 2, scale=2.0),
        cov_vxy=col(2, 2, scale=2.0), confidence=col(scale=0.8), age_s=col(scale=5.0), sources=rng.integers(0, 4, n))


def test_compiled_row_fit_equals_numpy_clip_and_wrap_bit_for_bit():
    from v2i.fusion import wire

    rng = np.random.default_rng(8)
    for n in (0, 1, 7, 500):
        real = rng.normal(0.0, 10.0, (n, 22)) * np.where(rng.random((n, 22)) < 0.3, 1e6, 1.0)
        real[rng.random(real.shape) < 0.1] = -0.0
        real[:, :2] = rng.uniform(-5000.0, 5000.0, (n, 2))
        real[-1:, 1] = -4500.0  # beyond a bound of 4000 m
        bounds = rng.integers(2, len(wire._W_LO), (n, 4))  # values exactly on a (finite) bound
        for i in range(n):
            real[i, bounds[i, 0]], real[i, bounds[i, 1]] = wire._W_LO[bounds[i, 0]], wire._W_HI[bounds[i, 1]]
        real[:, wire._W_YAW] = rng.choice([math.pi, -math.pi, 3 * math.pi, 0.0, -0.0, 1e6, -7.0], n)
        ids = rng.integers(-2**40, 2**40, n)
        want = np.clip(real, wire._W_LO, wire._W_HI)
        want[:, wire._W_YAW] = wrap_angle(real[:, wire._W_YAW])
        want_ids = np.mod(ids, 2**32)
        want_changed = int(((ids != want_ids) | (real != want).any(axis=1)).sum())
        got, got_ids = real.copy(), np.empty(n, np.int64)
        assert wire._fit_rows(got, ids, got_ids, wire._W_LO, wire._W_HI, wire._W_YAW, 4000.0) == (-1 if n else 0)
        assert np.array_equal(got, real)  # a position beyond the bound: untouched, for the general path
        assert wire._fit_rows(got, ids, got_ids, wire._W_LO, wire._W_HI, wire._W_YAW, 5000.0) == want_changed
        assert np.array_equal(got.view(np.int64), want.view(np.int64)) and np.array_equal(got_ids, want_ids)
    nan = np.zeros((2, 22))
    nan[1, 5] = np.nan
    assert wire._fit_rows(nan, np.zeros(2, np.int64), np.empty(2, np.int64), wire._W_LO, wire._W_HI, 3, 1.0) == -1
    fine = np.zeros((2, 22))
    assert wire._fit_rows(fine, np.zeros(2, np.int64), np.empty(2, np.int64), wire._W_LO, wire._W_HI, 3, 1.0) == 0
    for ids, out, lo in [(np.zeros(1, np.int64), np.empty(2, np.int64), wire._W_LO),
                         (np.zeros(2, np.int64), np.empty(1, np.int64), wire._W_LO),
                         (np.zeros(2, np.int64), np.empty(2, np.int64), wire._W_LO[:5])]:
        assert wire._fit_rows(fine, ids, out, lo, wire._W_HI, 3, 1.0) == -1  # lengths that disagree


def test_wire_columns_compiled_path_equals_fit_to_wire_then_states_from_objects():
    from v2i.fusion.wire import fit_to_wire, states_from_objects, wire_columns

    rng = np.random.default_rng(9)
    for n in (0, 1, 6, 300):
        objs = _finite_hostile(rng, n)
        fitted, counts = fit_to_wire(objs, 1024)
        assert n < 300 or counts["clipped"] > 0
        for fused in (False, True):
            cols, got_counts = wire_columns(objs, 1024, fused)
            assert got_counts == counts
            assert np.array_equal(cols.codes, states_from_objects(fitted, fused).codes)


def _table_fit(objs):
    """fit_to_wire's general (numpy) path when every row is kept: the table clipped by np.clip, yaw wrapped."""
    from v2i.fusion import wire

    table = wire._table(objs)
    clipped = np.clip(table, wire._LO, wire._HI)
    clipped[:, wire._YAW] = wrap_angle(table[:, wire._YAW])
    ids = np.mod(objs.ids, 2**32)
    changed = int(((objs.ids != ids) | (table != clipped).any(axis=1)).sum())
    return wire._with_table(objs.take(np.arange(len(objs))), ids, clipped), Counter(clipped=changed)


def test_fit_to_wire_compiled_path_equals_the_numpy_table_path_and_the_per_column_reference():
    import importlib.util
    from pathlib import Path

    from v2i.fusion.wire import fit_to_wire

    spec = importlib.util.spec_from_file_location("fit_reference", Path(__file__).with_name("test_fit_to_wire.py"))
    reference = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(reference)
    rng = np.random.default_rng(10)
    for n in (0, 1, 6, 300):
        objs = _finite_hostile(rng, n)
        fitted, counts = fit_to_wire(objs, 1024)
        table_fitted, table_counts = _table_fit(objs)
        ref, ref_counts = reference.reference_fit(objs, 1024)
        assert counts == +table_counts == ref_counts and (n < 300 or counts["clipped"] > 0)
        for name in ("ids", "cls", "xy", "z", "lwh", "yaw", "vxy", "axy", "yaw_rate", "cov_xy", "cov_vxy",
                     "confidence", "age_s", "sources"):
            got, want = getattr(fitted, name), getattr(table_fitted, name)
            np.testing.assert_array_equal(got, want, err_msg=name, strict=True)
            assert got.dtype.kind in "iu" or np.array_equal(np.signbit(got), np.signbit(want)), name  # signed zeros
            np.testing.assert_array_equal(got, getattr(ref, name), err_msg=name, strict=True)
        assert fitted.cls is not objs.cls and fitted.sources is not objs.sources
