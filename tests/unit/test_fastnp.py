"""fusion.fastnp gives what the usual numpy spelling gives."""

import numpy as np
import pytest

from fusion.fastnp import any_true, true_index


@pytest.mark.parametrize("shape", [(0,), (1,), (7,), (40,), (3, 5), (0, 4)])
def test_the_cheap_spellings_equal_numpy(shape):
    rng = np.random.default_rng(sum(shape))
    for p in (0.0, 0.3, 1.0):
        mask = rng.random(shape) < p
        ints = np.where(mask, rng.integers(1, 9, shape), 0)
        for a in (mask, ints):
            assert any_true(a) == a.any()
            np.testing.assert_array_equal(true_index(a), np.flatnonzero(a))
            assert true_index(a).dtype == np.flatnonzero(a).dtype
