"""A few numpy idioms with less fixed cost per call, for the tracker's small per-update arrays.

On arrays of tens of elements numpy's per-call overhead is the whole cost, and some spellings pay
a Python-level wrapper the others skip (numpy 2.4, this machine, 40-260 elements):
``mask.any()`` / ``.all()`` ~0.7 us against ``np.count_nonzero`` ~0.17 us; ``np.flatnonzero``
~0.8 us against ``mask.nonzero()[0]`` ~0.2 us; ``np.ones`` ~0.65 us against ``np.empty`` + ``fill``
~0.25 us; ``np.linalg.cholesky`` / ``inv`` / ``eigvalsh`` ~2.5 us of checks around the LAPACK gufunc
they call (``cholesky_or_nan`` ...: the gufunc itself; NaN for a failed matrix instead of an error).
The functions here give the same results as the usual spelling (tests/unit/test_fastnp.py).
"""

from __future__ import annotations

import numpy as np


def any_true(a: np.ndarray) -> bool:
    """``a.any()``: some element nonzero (True)."""
    return np.count_nonzero(a) > 0


def all_true(a: np.ndarray) -> bool:
    """``a.all()``: every element nonzero (True); True for an empty array."""
    return np.count_nonzero(a) == a.size


def true_index(a: np.ndarray) -> np.ndarray:
    """``np.flatnonzero(a)``: indices (int64) of the nonzero elements of the flattened array, in order."""
    return a.ravel().nonzero()[0]


def filled(n: int, value, dtype=float) -> np.ndarray:
    """``np.full(n, value, dtype)`` (and ``np.ones`` for value 1): a new (n,) array."""
    out = np.empty(n, dtype)
    out.fill(value)
    return out


# Batched LAPACK: np.linalg.cholesky / inv / eigvalsh call these gufuncs after ~2.5 us of Python-level checks
# and an errstate that turns a failure into a LinAlgError for the whole batch. Called directly (float64
# only), a matrix without a result comes back as NaN and the others are unaffected (the same LAPACK calls,
# so the same numbers). A numpy without the (private) module gets the public functions matrix by matrix.
try:
    from numpy.linalg import _umath_linalg as _lapack
except ImportError:  # pragma: no cover (numpy 1.26 - 2.4 have it; tests run both paths)
    _lapack = None


def _each_or_nan(fn, a: np.ndarray) -> np.ndarray:
    """fn (a public np.linalg function) of each matrix a[k] (K, m, m); all NaN where it raises LinAlgError."""
    rows = []
    for matrix in a:
        try:
            rows.append(fn(matrix))
        except np.linalg.LinAlgError:
            rows.append(None)
    shape = next((r.shape for r in rows if r is not None), fn(np.eye(a.shape[-1])).shape)
    return np.array([np.full(shape, np.nan) if r is None else r for r in rows]).reshape(len(a), *shape)


def cholesky_or_nan(a: np.ndarray) -> np.ndarray:
    """``np.linalg.cholesky`` (lower) of each float64 matrix a (K, m, m); all NaN for a matrix without a factor."""
    if _lapack is None:
        return _each_or_nan(np.linalg.cholesky, a)
    with np.errstate(all="ignore"):
        return _lapack.cholesky_lo(a, signature="d->d")


def inverse_cholesky_or_nan(a: np.ndarray) -> np.ndarray:
    """``np.linalg.inv(np.linalg.cholesky(a))`` of each float64 matrix a (K, m, m): L^-1 with a = L L^T (a
    whitening transform, L^-1 a L^-T = I); all NaN for a matrix without a factor. One errstate for both."""
    if _lapack is None:
        return inv_or_nan(cholesky_or_nan(a))
    with np.errstate(all="ignore"):
        return _lapack.inv(_lapack.cholesky_lo(a, signature="d->d"), signature="d->d")


def inv_or_nan(a: np.ndarray) -> np.ndarray:
    """``np.linalg.inv`` of each float64 matrix a (K, m, m); all NaN for a singular one."""
    if _lapack is None:
        return _each_or_nan(np.linalg.inv, a)
    with np.errstate(all="ignore"):
        return _lapack.inv(a, signature="d->d")


def eigvalsh_or_nan(a: np.ndarray) -> np.ndarray:
    """``np.linalg.eigvalsh`` (lower triangle, ascending) of each float64 symmetric matrix a (K, m, m);
    NaN where LAPACK does not converge."""
    if _lapack is None:
        return _each_or_nan(np.linalg.eigvalsh, a)
    with np.errstate(all="ignore"):
        return _lapack.eigvalsh_lo(a, signature="d->d")
