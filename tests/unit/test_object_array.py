"""ObjectArray construction defaults and the with_ fast path keep the row-count checks."""

import numpy as np
import pytest

from v2i.core.objects import ObjectArray
from schemas.messages import UNKNOWN_VELOCITY_VAR


def objects(n: int) -> ObjectArray:
    return ObjectArray(ids=np.arange(n), cls=np.ones(n, int), xy=np.zeros((n, 2)), z=np.zeros(n),
                       lwh=np.ones((n, 3)), yaw=np.zeros(n), vxy=np.zeros((n, 2)))


def test_defaults_fill_only_the_columns_left_out():
    objs = ObjectArray(ids=np.arange(2), cls=np.ones(2, int), xy=np.zeros((2, 2)), z=np.zeros(2),
                       lwh=np.ones((2, 3)), yaw=np.zeros(2), vxy=np.zeros((2, 2)), confidence=np.array([0.3, 0.4]))
    np.testing.assert_array_equal(objs.confidence, [0.3, 0.4])
    np.testing.assert_array_equal(objs.cov_xy, np.tile(np.eye(2), (2, 1, 1)))
    np.testing.assert_array_equal(objs.cov_vxy, np.tile(np.eye(2) * UNKNOWN_VELOCITY_VAR, (2, 1, 1)))
    assert objs.sources.dtype == np.int64 and objs.axy.shape == (2, 2) and objs.age_s.shape == (2,)
    with pytest.raises(ValueError, match="xy has 1 rows"):
        ObjectArray(ids=np.arange(2), cls=np.ones(2, int), xy=np.zeros((1, 2)), z=np.zeros(2),
                    lwh=np.ones((2, 3)), yaw=np.zeros(2), vxy=np.zeros((2, 2)))


@pytest.mark.parametrize("n", [0, 1, 5, 64, 65, 300, 3])
def test_default_covariances_are_fresh_tiles_bit_for_bit(n):
    """The kept tiles give np.tile's arrays (bytes, shape, layout), each a fresh writable copy."""
    a, b = objects(n), objects(n)
    for got, variance in ((a.cov_xy, 1.0), (a.cov_vxy, UNKNOWN_VELOCITY_VAR)):
        want = np.tile(np.eye(2) * variance, (n, 1, 1))
        assert got.shape == want.shape and got.tobytes() == want.tobytes() and got.flags.c_contiguous
        assert got.flags.writeable and got.flags.owndata
    if n:
        a.cov_xy[0, 0, 0] = a.cov_vxy[0, 0, 0] = 7.0
        assert b.cov_xy[0, 0, 0] == 1.0 and b.cov_vxy[0, 0, 0] == UNKNOWN_VELOCITY_VAR


def test_with_replaces_columns_and_still_refuses_a_wrong_row_count():
    objs = objects(3)
    moved = objs.with_(xy=np.ones((3, 2)), yaw=np.full(3, 0.5))
    np.testing.assert_array_equal(moved.xy, np.ones((3, 2)))
    np.testing.assert_array_equal(objs.xy, np.zeros((3, 2)))  # the original is unchanged
    assert moved.lwh is objs.lwh and isinstance(moved, ObjectArray) and len(moved) == 3
    with pytest.raises(ValueError, match="xy has 2 rows"):
        objs.with_(xy=np.ones((2, 2)))
    with pytest.raises(ValueError, match="has 3 rows, ids has 2"):
        objs.with_(ids=np.arange(2))  # new ids of another length: every column is checked against them
    renamed = objs.with_(ids=np.arange(10, 13), xy=np.ones((3, 2)))  # new ids of N rows: the fast path
    assert renamed.ids.tolist() == [10, 11, 12] and renamed.lwh is objs.lwh and objs.ids.tolist() == [0, 1, 2]
    with pytest.raises(ValueError, match="has 3 rows, ids has 2"):
        objs.with_(ids=np.arange(2), xy=np.ones((2, 2)))
    with pytest.raises(TypeError):
        objs.with_(colour=np.ones(3))
    assert objs.with_(confidence=None).confidence.tolist() == [1.0, 1.0, 1.0]  # None: the default again


def _random_objects(n: int, rng: np.random.Generator) -> ObjectArray:
    return ObjectArray(ids=rng.integers(0, 1000, n), cls=rng.integers(0, 5, n), xy=rng.normal(size=(n, 2)),
                       z=rng.normal(size=n), lwh=rng.random((n, 3)), yaw=rng.normal(size=n),
                       vxy=rng.normal(size=(n, 2)),
                       axy=rng.normal(size=(n, 2)), yaw_rate=rng.normal(size=n), cov_xy=rng.normal(size=(n, 2, 2)),
                       confidence=rng.random(n), cov_vxy=rng.normal(size=(n, 2, 2)), age_s=rng.random(n),
                       sources=rng.integers(0, 8, n))


@pytest.mark.parametrize("index", [
    np.array([True, False, True, True, False, False, True]), [False] * 7, [2, 0, 6, 6],
    np.array([-1, 3], np.int64), np.array([4], np.int32), 5, np.int64(-2), [], np.zeros(0, np.int64),
    [True, False, True, False, False, False, True]])
def test_take_selects_the_rows_each_column_indexing_selects(index):
    objs = _random_objects(7, np.random.default_rng(3))
    expected = {name: np.asarray(getattr(objs, name))[[index] if np.ndim(index) == 0 else index]
                for name in objs.__dataclass_fields__}
    taken = objs.take(index)
    for name, column in expected.items():
        got = getattr(taken, name)
        assert got.dtype == column.dtype and got.shape == column.shape, name
        np.testing.assert_array_equal(got, column)


def test_take_refuses_what_indexing_refuses():
    objs = _random_objects(4, np.random.default_rng(4))
    with pytest.raises(IndexError):
        objs.take(np.array([True, False]))  # a mask of another length
    with pytest.raises(IndexError):
        objs.take([4])


def test_init_takes_the_dataclass_fields_in_order():
    """ObjectArray's own __init__ (the frozen fields set at once) has the dataclass's signature: every field in
    order, the optional ones defaulting to None; positional and keyword calls give the same columns."""
    import dataclasses
    import inspect

    fields = dataclasses.fields(ObjectArray)
    params = list(inspect.signature(ObjectArray.__init__).parameters.values())[1:]
    assert [p.name for p in params] == [f.name for f in fields]
    assert [p.default for p in params] == [inspect.Parameter.empty if f.default is dataclasses.MISSING else f.default
                                           for f in fields]
    rng = np.random.default_rng(0)
    columns = [rng.normal(size=(3, *shape)) for shape in ((), (), (2,), (), (3,), (), (2,), (2,), (), (2, 2), (), (2, 2),
                                                         (), ())]
    by_position, by_name = ObjectArray(*columns), ObjectArray(**{f.name: c for f, c in zip(fields, columns)})
    assert list(by_position.__dict__) == [f.name for f in fields]
    for f, c in zip(fields, columns):
        assert getattr(by_position, f.name) is c and getattr(by_name, f.name) is c
    assert dataclasses.replace(by_name, z=columns[0]).z is columns[0]
