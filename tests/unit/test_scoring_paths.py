"""The scoring's shorter expressions (evaluation.metrics) against the numpy expressions they replace,
bit for bit: ranges from the ego, a box's BEV row, a pair's squared error."""

import numpy as np

from evaluation.metrics import _bev_row, _ranges_m
from fusion.objects import ObjectArray


def _hard_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 2) points of every scale, with zeros, signed zeros, subnormals, huge values, NaN and inf."""
    xy = rng.normal(0.0, 1.0, (n, 2)) * 10.0 ** rng.integers(-6, 6, (n, 2))
    specials = np.array([0.0, -0.0, 5e-324, -5e-324, 1e-160, 1e154, 1e200, -1e200, np.nan, np.inf, -np.inf, 80.0])
    pick = rng.random((n, 2)) < 0.1
    xy[pick] = rng.choice(specials, int(pick.sum()))
    return xy


def test_ranges_equal_linalg_norm_bit_for_bit():
    rng = np.random.default_rng(3)
    with np.errstate(over="ignore", invalid="ignore"):
        for n in (0, 1, 2, 7, 1000):
            xy = _hard_points(rng, n)
            assert _ranges_m(xy).tobytes() == np.linalg.norm(xy, axis=1).tobytes()


def test_squared_error_of_two_terms_equals_sum_of_squares():
    rng = np.random.default_rng(4)
    with np.errstate(over="ignore", invalid="ignore"):
        for a, b in zip(_hard_points(rng, 4000), _hard_points(rng, 4000)):
            err = b - a
            ex, ey = b[0] - a[0], b[1] - a[1]
            got, want = ex * ex + ey * ey, float(np.sum(np.square(err)))
            assert np.array([got]).tobytes() == np.array([want]).tobytes()


def test_bev_row_equals_the_concatenation():
    rng = np.random.default_rng(5)
    n = 50
    objs = ObjectArray(ids=np.arange(n), cls=np.zeros(n, np.int64), xy=_hard_points(rng, n), z=np.zeros(n),
                       lwh=np.abs(rng.normal(3.0, 1.0, (n, 3))), yaw=rng.uniform(-4.0, 4.0, n), vxy=np.zeros((n, 2)))
    for i in range(n):
        want = np.concatenate([objs.xy[i], objs.lwh[i, :2], [objs.yaw[i]]])
        assert _bev_row(objs, i).tobytes() == want.tobytes()
