"""fusion.fastnp gives what the usual numpy spelling gives."""

import numpy as np
import pytest

from fusion import fastnp
from fusion.fastnp import (all_true, any_true, cholesky_or_nan, eigvalsh_or_nan, filled, inv_or_nan,
                           inverse_cholesky_or_nan, true_index)


@pytest.mark.parametrize("shape", [(0,), (1,), (7,), (40,), (3, 5), (0, 4)])
def test_the_cheap_spellings_equal_numpy(shape):
    rng = np.random.default_rng(sum(shape))
    for p in (0.0, 0.3, 1.0):
        mask = rng.random(shape) < p
        ints = np.where(mask, rng.integers(1, 9, shape), 0)
        for a in (mask, ints):
            assert any_true(a) == a.any() and all_true(a) == a.all()
            np.testing.assert_array_equal(true_index(a), np.flatnonzero(a))
            assert true_index(a).dtype == np.flatnonzero(a).dtype
    n = shape[0]
    for value, dtype in ((True, bool), (1.0, float), (-np.inf, float), (3, np.int64)):
        out = filled(n, value, dtype)
        np.testing.assert_array_equal(out, np.full(n, value, dtype))
        assert out.dtype == np.full(n, value, dtype).dtype


@pytest.mark.parametrize("private", [True, False], ids=["gufuncs", "public-fallback"])
@pytest.mark.parametrize("m", [2, 4])
def test_batched_lapack_equals_numpy_linalg_and_marks_failures_nan(m, private, monkeypatch):
    """The same LAPACK calls as np.linalg (bit for bit); a matrix without a result is NaN, the others
    unaffected; the same through the public functions when numpy lacks the private gufunc module."""
    if not private:
        monkeypatch.setattr(fastnp, "_lapack", None)
    rng = np.random.default_rng(m)
    a = rng.normal(size=(6, m, m))
    spd = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(m)
    np.testing.assert_array_equal(cholesky_or_nan(spd), np.linalg.cholesky(spd))
    np.testing.assert_array_equal(inv_or_nan(a), np.linalg.inv(a))
    np.testing.assert_array_equal(eigvalsh_or_nan(spd), np.linalg.eigvalsh(spd))
    assert cholesky_or_nan(spd[:0]).shape == (0, m, m)
    broken = spd.copy()
    broken[2] = -np.eye(m)  # no Cholesky factor
    broken[4, 0, 0] = 0.0  # nor this one
    broken[4, 0, 1:] = broken[4, 1:, 0] = 0.0
    chol = cholesky_or_nan(broken)
    assert np.isnan(chol[[2, 4]]).all()
    np.testing.assert_array_equal(chol[[0, 1, 3, 5]], np.linalg.cholesky(spd[[0, 1, 3, 5]]))
    whitening = inverse_cholesky_or_nan(broken)
    assert np.isnan(whitening[[2, 4]]).all()
    np.testing.assert_array_equal(whitening[[0, 1, 3, 5]], np.linalg.inv(np.linalg.cholesky(spd[[0, 1, 3, 5]])))
    singular = a.copy()
    singular[1] = 0.0
    inv = inv_or_nan(singular)
    assert np.isnan(inv[1]).all()
    np.testing.assert_array_equal(inv[[0, 2, 3, 4, 5]], np.linalg.inv(a[[0, 2, 3, 4, 5]]))
