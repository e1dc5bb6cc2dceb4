"""v2i.fusion.motion.predict_ca's scalar step equals the broadcast (N, 1) column of the original expression bit for bit."""

import numpy as np
import pytest

from v2i.fusion.motion import predict_ca
from v2i.core.objects import ObjectArray


def _reference_ca(objs: ObjectArray, dt_s) -> ObjectArray:
    """The expression predict_ca had for every dt: dt broadcast to an (N, 1) float64 column."""
    dt = np.broadcast_to(np.asarray(dt_s, dtype=float), (len(objs),))[:, None]
    return objs.with_(xy=objs.xy + objs.vxy * dt + 0.5 * objs.axy * dt**2, vxy=objs.vxy + objs.axy * dt,
                      age_s=objs.age_s + np.maximum(dt[:, 0], 0.0))


def _objects(n: int, rng: np.random.Generator, dtype=np.float64) -> ObjectArray:
    return ObjectArray(ids=np.arange(n), cls=np.ones(n, np.int64), xy=rng.normal(0, 50, (n, 2)).astype(dtype),
                       z=np.zeros(n), lwh=np.ones((n, 3)), yaw=np.zeros(n), vxy=rng.normal(0, 10, (n, 2)).astype(dtype),
                       axy=rng.normal(0, 2, (n, 2)).astype(dtype), age_s=rng.random(n).astype(dtype))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_scalar_step_is_the_broadcast_column_bit_for_bit(dtype):
    rng = np.random.default_rng(7)
    steps = [float(s) for s in rng.normal(0, 0.3, 300)]
    steps += [0.0, -0.0, 1e-300, -1e-300, 3, np.float64(0.137), float("nan")]
    for dt in steps:
        objs = _objects(int(rng.integers(0, 9)), rng, dtype)
        got, want = predict_ca(objs, dt), _reference_ca(objs, dt)
        for name in ("xy", "vxy", "age_s"):
            a, b = getattr(got, name), getattr(want, name)
            assert a.dtype == b.dtype, (name, dt)
            np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8))  # bits, signed zeros and NaN included


def test_per_object_steps_keep_the_broadcast():
    rng = np.random.default_rng(8)
    objs = _objects(5, rng)
    dt = rng.normal(0, 0.3, 5)
    np.testing.assert_array_equal(predict_ca(objs, dt).xy, _reference_ca(objs, dt).xy)
