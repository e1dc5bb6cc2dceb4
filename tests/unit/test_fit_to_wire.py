"""v2i.fusion.wire.fit_to_wire (one stacked (N, 22) table) against the per-column reference it replaced, and
wire_columns (fit and wire columns from one table) against fit_to_wire then states_from_objects."""

from collections import Counter

import numpy as np
import pytest

from v2i.core.frames import wrap_angle
from v2i.core.objects import ObjectArray
from v2i.fusion.wire import fit_to_wire, states_from_objects, wire_columns
from schemas import messages as m
from schemas.errors import InvalidMessage


def reference_fit(objs: ObjectArray, max_objects: int) -> tuple[ObjectArray, Counter]:
    """fit_to_wire before the table (commit 723e2c2): each column checked and clipped on its own."""
    def rows(a):
        return a.reshape(len(a), int(np.prod(a.shape[1:], dtype=int)))

    def values(o):
        return [o.xy, o.z, o.lwh, o.yaw, o.vxy, o.axy, o.yaw_rate, o.cov_xy, o.cov_vxy, o.confidence, o.age_s]

    def cov(c):
        out = np.clip(c, -m.VARIANCE_MAX, m.VARIANCE_MAX)
        out[:, [0, 1], [0, 1]] = np.clip(c[:, [0, 1], [0, 1]], 0.0, m.VARIANCE_MAX)
        return out

    finite = np.ones(len(objs), bool)
    for column in values(objs):
        finite &= np.isfinite(rows(column)).all(axis=1)
    inside = finite & (np.abs(np.where(finite[:, None], objs.xy, 0.0)) <= m.POSITION_MAX_M).all(axis=1)
    counts = Counter(not_finite=int((~finite).sum()), out_of_range=int((finite & ~inside).sum()))
    objs = objs.take(inside)
    if len(objs) > max_objects:
        counts["truncated"] = len(objs) - max_objects
        objs = objs.take(np.sort(np.argsort(np.hypot(objs.xy[:, 0], objs.xy[:, 1]), kind="stable")[:max_objects]))
    clipped = objs.with_(
        ids=np.mod(objs.ids, 2**32), z=np.clip(objs.z, -m.HEIGHT_MAX_M, m.HEIGHT_MAX_M),
        lwh=np.clip(objs.lwh, 0.0, m.SIZE_MAX_M), yaw=wrap_angle(objs.yaw),
        vxy=np.clip(objs.vxy, -m.SPEED_MAX_MPS, m.SPEED_MAX_MPS),
        axy=np.clip(objs.axy, -m.ACCEL_MAX_MPS2, m.ACCEL_MAX_MPS2),
        yaw_rate=np.clip(objs.yaw_rate, -m.YAW_RATE_MAX, m.YAW_RATE_MAX), cov_xy=cov(objs.cov_xy),
        cov_vxy=cov(objs.cov_vxy), confidence=np.clip(objs.confidence, 0.0, 1.0),
        age_s=np.clip(objs.age_s, 0.0, m.AGE_MAX_S))
    changed = objs.ids != clipped.ids
    for before, after in zip(values(objs), values(clipped)):
        changed |= rows(before != after).any(axis=1)
    counts["clipped"] = int(changed.sum())
    return clipped, +counts


def hostile_objects(rng: np.random.Generator, n: int) -> ObjectArray:
    """n objects whose values are mostly in range, some far out of it, some non-finite."""
    def col(*shape, scale):
        a = rng.normal(0.0, scale, (n, *shape)) * np.where(rng.random((n, *shape)) < 0.1, 1e4, 1.0)
        a[rng.random(a.shape) < 0.01] = rng.choice([np.nan, np.inf, -np.inf])
        return a

    return ObjectArray(
        ids=rng.integers(-2**40, 2**40, n), cls=rng.integers(0, 5, n), xy=col(2, scale=300.0), z=col(scale=1.0),
        lwh=col(3, scale=3.0), yaw=col(scale=4.0), vxy=col(2, scale=20.0), axy=col(2, scale=3.0),
        yaw_rate=col(scale=0.5), cov_xy=col(2, 2, scale=2.0), cov_vxy=col(2, 2, scale=2.0),
        confidence=col(scale=0.8), age_s=col(scale=5.0), sources=rng.integers(0, 4, n))


def test_fit_to_wire_equals_the_per_column_reference_exactly():
    rng = np.random.default_rng(7)
    for n, max_objects in [(0, 10), (1, 10), (40, 1000), (300, 50), (300, 0)]:
        objs = hostile_objects(rng, n)
        fitted, counts = fit_to_wire(objs, max_objects)
        ref, ref_counts = reference_fit(objs, max_objects)
        assert counts == ref_counts
        assert n < 40 or counts["not_finite"] > 0 and counts["out_of_range"] > 0
        assert n < 40 or max_objects == 0 or counts["clipped"] > 0
        for name in ("ids", "cls", "xy", "z", "lwh", "yaw", "vxy", "axy", "yaw_rate", "cov_xy", "cov_vxy",
                     "confidence", "age_s", "sources"):
            got, want = getattr(fitted, name), getattr(ref, name)
            assert got.shape == want.shape and got.dtype == want.dtype, name
            np.testing.assert_array_equal(got, want, err_msg=name, strict=True)


def test_wire_columns_equals_fit_to_wire_then_states_from_objects():
    """One table (wire_columns) gives the codes and counts of fit_to_wire followed by
    states_from_objects, plain and fused, hostile values and truncation included; an object
    the wire refuses after fitting (a class code out of range) raises the same error."""
    rng = np.random.default_rng(11)
    for n, max_objects in [(0, 10), (1, 10), (40, 1000), (300, 50), (300, 0), (200, 1024)]:
        objs = hostile_objects(rng, n)
        if n == 200:  # symmetric covariances, as a tracker's: nothing but lower off-diagonals differ
            objs = objs.with_(cov_xy=objs.cov_xy + objs.cov_xy.transpose(0, 2, 1),
                              cov_vxy=objs.cov_vxy + objs.cov_vxy.transpose(0, 2, 1))
        fitted, counts = fit_to_wire(objs, max_objects)
        for fused in (False, True):
            cols, got_counts = wire_columns(objs, max_objects, fused)
            want = states_from_objects(fitted, fused)
            assert got_counts == counts and cols.fused == fused
            np.testing.assert_array_equal(cols.codes, want.codes, strict=True)
    bad = hostile_objects(rng, 30)
    bad = bad.with_(cls=np.where(np.arange(30) == 7, 999, bad.cls))
    fitted, _ = fit_to_wire(bad)
    with pytest.raises(InvalidMessage) as want:
        states_from_objects(fitted, True)
    with pytest.raises(InvalidMessage) as got:
        wire_columns(bad, fused=True)
    assert str(got.value) == str(want.value) and "cls" in str(got.value)


def test_wire_columns_counts_a_clip_of_the_lower_off_diagonal_alone():
    """fit_to_wire clips (and counts) all four covariance entries; the wire carries three, so a
    row whose cov_xy[1, 0] alone is out of range is counted clipped by both."""
    objs = hostile_objects(np.random.default_rng(3), 1)
    objs = objs.with_(xy=np.zeros((1, 2)), z=np.zeros(1), lwh=np.ones((1, 3)), yaw=np.zeros(1), vxy=np.zeros((1, 2)),
                      axy=np.zeros((1, 2)), yaw_rate=np.zeros(1), confidence=np.ones(1), age_s=np.zeros(1),
                      ids=np.ones(1, np.int64), cov_xy=np.array([[[1.0, 0.0], [2 * m.VARIANCE_MAX, 1.0]]]),
                      cov_vxy=np.tile(np.eye(2), (1, 1, 1)))
    assert fit_to_wire(objs)[1] == wire_columns(objs)[1] == Counter(clipped=1)


def test_every_row_kept_fast_path_equals_the_reference():
    """Finite objects inside the position range (every row kept: the one-pass check), with and
    without truncation, some still clipped (speeds, yaw): the reference's rows, values and counts."""
    rng = np.random.default_rng(5)
    for n, max_objects in [(1, 10), (50, 1000), (50, 20), (50, 0)]:
        objs = hostile_objects(rng, n)
        objs = objs.with_(**{name: np.nan_to_num(getattr(objs, name), nan=0.5, posinf=2.0, neginf=-2.0)
                             for name in ("xy", "z", "lwh", "yaw", "vxy", "axy", "yaw_rate", "cov_xy", "cov_vxy",
                                          "confidence", "age_s")})
        objs = objs.with_(xy=np.clip(objs.xy, -m.POSITION_MAX_M, m.POSITION_MAX_M))
        fitted, counts = fit_to_wire(objs, max_objects)
        ref, ref_counts = reference_fit(objs, max_objects)
        assert counts == ref_counts and "not_finite" not in counts and "out_of_range" not in counts
        assert n < 50 or max_objects == 0 or counts["clipped"] > 0
        assert counts["truncated"] == max(0, n - max_objects)
        for name in ("ids", "xy", "yaw", "vxy", "cov_xy", "sources"):
            np.testing.assert_array_equal(getattr(fitted, name), getattr(ref, name), err_msg=name, strict=True)
        cols, cols_counts = wire_columns(objs, max_objects, fused=True)
        assert cols_counts == counts and np.array_equal(cols.codes, states_from_objects(fitted, True).codes)


def test_gathered_covariances_are_advanced_indexing_values_and_layout():
    """objects_from_states' covariance columns (``_gathered``): the values and the strides of v[:, columns]."""
    from v2i.fusion import wire

    rng = np.random.default_rng(4)
    for n in (0, 1, 2, 6, 41):
        v = rng.normal(size=(n, 23))
        for columns in (wire._COV, wire._VCOV):
            got, want = wire._gathered(v, columns), v[:, list(columns)]
            assert got.shape == want.shape and got.strides == want.strides and got.tobytes() == want.tobytes()
            assert got.reshape(n, 2, 2).strides == want.reshape(n, 2, 2).strides
