"""``v2i.fusion.lsap.linear_sum_assignment`` is scipy's own function, loaded from its extension module without
importing the ``scipy.optimize`` package (v2i.core.jit.import_extension)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np


def test_it_is_scipys_function_without_the_scipy_optimize_package():
    """A fresh interpreter: v2i.fusion.lsap loads no scipy.optimize package; scipy.optimize imported afterwards
    exports the very same function, and it matches (scipy's own example)."""
    code = """
import sys
from v2i.fusion.lsap import linear_sum_assignment
assert "scipy.optimize" not in sys.modules, sorted(m for m in sys.modules if m.startswith("scipy.optimize"))
rows, cols = linear_sum_assignment([[4, 1, 3], [2, 0, 5], [3, 2, 2]])
import scipy.optimize
assert scipy.optimize.linear_sum_assignment is linear_sum_assignment
print(rows.tolist(), cols.tolist())
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.split("\n")[0] == "[0, 1, 2] [1, 0, 2]", out.stderr


def test_import_extension_finds_extension_modules_only():
    from v2i.core.jit import import_extension

    lsap = import_extension("scipy.optimize._lsap")
    assert sys.modules["scipy.optimize._lsap"] is lsap
    rows, cols = lsap.linear_sum_assignment(np.zeros((2, 3)), maximize=True)
    assert rows.tolist() == [0, 1] and len(set(cols.tolist())) == 2
    assert import_extension("scipy.optimize._no_such_module") is None
    assert import_extension("scipy.optimize._no_such_module") is None and "scipy.optimize._no_such_module" not in sys.modules
