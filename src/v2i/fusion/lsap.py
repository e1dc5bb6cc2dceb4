"""Linear sum assignment: ``scipy.optimize.linear_sum_assignment`` (the shortest augmenting path
algorithm of D. F. Crouse, "On implementing 2D rectangular assignment algorithms", IEEE TAES 52(4),
2016), taken from its extension module ``scipy.optimize._lsap`` alone.

Importing the ``scipy.optimize`` package runs its ``__init__`` (linalg, sparse, fft and the rest:
~0.3 s on a 2-core machine), most of scipy's time in a service that needs nothing else of it; the
extension module itself loads in under a millisecond (``v2i.core.jit.import_extension``), and it is
the very function ``scipy.optimize`` exports. Where it is not found (another scipy layout) the
package is imported as usual. On the assignments of a cycle benchmark and an evaluated run scipy's
call is faster than the compiled copy of its algorithm that was here (3.1 against 5.5 us per call
in ``benchmarks/cycle_compute.py``, 0.7 against 2.0 us in a connected-intersection run).
"""

from __future__ import annotations

from v2i.core.jit import import_extension

_lsap = import_extension("scipy.optimize._lsap")
if _lsap is None:  # pragma: no cover  (a scipy without the extension module where 1.17 has it)
    from scipy.optimize import linear_sum_assignment
else:
    linear_sum_assignment = _lsap.linear_sum_assignment

__all__ = ["linear_sum_assignment"]
