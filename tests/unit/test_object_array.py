"""ObjectArray construction defaults and the with_ fast path keep the row-count checks."""

import numpy as np
import pytest

from fusion.objects import ObjectArray
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
