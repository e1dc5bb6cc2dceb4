"""The roadside camera reports each class's prior size (a table lookup per class code)."""

from __future__ import annotations

import numpy as np

from schemas.classes import CLASS_DEFAULT_LWH, ObjectClass
from v2i.sim.sensors import _default_lwh


def test_prior_sizes_by_class_code_match_the_table():
    codes = np.random.default_rng(2).integers(0, len(ObjectClass), 300)
    want = np.array([CLASS_DEFAULT_LWH[ObjectClass(int(c))] for c in codes])
    np.testing.assert_array_equal(_default_lwh(codes), want)
    np.testing.assert_array_equal(_default_lwh(np.array([ObjectClass.BUS])), [[12.0, 2.55, 3.2]])
    assert _default_lwh(np.zeros(0, dtype=np.int64)).shape == (0, 3)
