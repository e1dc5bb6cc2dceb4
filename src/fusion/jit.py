"""Compiled kernels (numba): the tracker's per-pair loops and assignment solver, the OBU's clock
fit and input checks, the simulator's line of sight and body states, the rotated-box IoU, the
codec's bit packing, the fitting of objects to the wire, lane matching and the evaluation's
per-frame detection matching.

The tracker updates a few hundred tracks with lists of a few to a few hundred objects, ten
times a second per source: numpy's fixed cost per call (~1 us, some 200 calls per update) was
the whole cost, so association, the Kalman updates, covariance intersection and the matched
tracks' bookkeeping are loops over the pairs, compiled by numba (``benchmarks/cycle_compute.py``;
the numpy and filterpy references are in the tests). So are the clock fit of
``obu_service.clock_envelope`` (a window of exchanges, refitted every few exchanges per RSU and
peer), ``sim.occlusion``'s test of sample points against occluders, ``sim.world``'s body states
along their paths, ``evaluation.detection_metrics``' matches per frame, ``fusion.geometry``'s IoU
(shapely's polygons cost ~30 us a pair), ``schemas.bit_rows`` (used once loaded: see
``schemas.bitpack``) and ``fusion.lsap``'s assignment solver (scipy's algorithm: importing
``scipy.optimize`` for it cost each service ~0.15 s of its start-up).

``kernel(*argument_types)`` compiles a function for exactly those argument types (and no
others) at its first call, or when ``load_kernels`` loads every kernel: the services and the
offline evaluator do that before they start, so that no cycle ever waits for the compiler. The
machine code is cached under ``__pycache__`` (or the user's cache directory where the package is
not writable): compiled once per machine (36 s for the 30 kernels, measured on a 2-core machine),
then loaded in ~0.3-0.4 s per process (most of it numba's own set-up at the first load; its check for
BLAS and LAPACK reaches scipy's two Cython modules directly: ``preload_scipy_blas``). Inputs are declared read-only arrays of any layout (``IN_*``: writable and strided
arrays convert to them), the arrays a kernel writes ``OUT_*``; an array of another dtype is a
``TypeError`` (callers pass float64 and int64). ``helper`` is for the functions the kernels
call (compiled into them). numba checks a cached kernel against its own source file only: the
helpers a kernel calls live in its module, and after a change to ``OPTIONS`` here the cached
files (``__pycache__/*.nbi``, ``*.nbc``) must be deleted. Kernels are loops, not numpy's array
expressions, sorts or quantiles where they can be: each of those adds ~0.1-1 s to a compile.
"""

from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import sys
import time
from pathlib import Path
from typing import Callable

from numba import njit, types

IN_F1, IN_F2, IN_F3 = (types.Array(types.float64, n, "A", readonly=True) for n in (1, 2, 3))
IN_I1 = types.Array(types.int64, 1, "A", readonly=True)
IN_I2 = types.Array(types.int64, 2, "A", readonly=True)
IN_U1 = types.Array(types.uint8, 1, "A", readonly=True)
IN_B2 = types.Array(types.boolean, 2, "A", readonly=True)
OUT_F1, OUT_F2, OUT_F3 = (types.Array(types.float64, n, "A") for n in (1, 2, 3))
OUT_I1 = types.Array(types.int64, 1, "A")
OUT_B1 = types.Array(types.boolean, 1, "A")
I64, F64, B1 = types.int64, types.float64, types.boolean

# error_model="numpy": a division by zero gives inf / NaN as in numpy (the callers test for them), not an exception
OPTIONS = dict(cache=True, nogil=True, error_model="numpy")
helper = njit(**OPTIONS)


class Kernel:
    """A function compiled by numba for one tuple of argument types, on its first call or ``load``."""

    _all: list[Kernel] = []

    def __init__(self, fn: Callable, argument_types: tuple):
        self.fn, self.argument_types = fn, argument_types
        self._compiled: Callable | None = None
        Kernel._all.append(self)

    def __call__(self, *args):
        return (self._compiled or self.load())(*args)

    def load(self) -> Callable:
        """The compiled function (loaded from the cache, or compiled and cached)."""
        if self._compiled is None:
            self._compiled = njit(self.argument_types, **OPTIONS)(self.fn)
        return self._compiled


def kernel(*argument_types) -> Callable[[Callable], Kernel]:
    """Decorator: the function as a ``Kernel`` for these argument types."""
    return lambda fn: Kernel(fn, argument_types)


# the modules that declare kernels (with the modules they import): load_kernels imports them. The
# evaluation's (evaluation.detection_metrics) are not listed, so that no service imports them: the
# offline evaluator has imported them before it calls load_kernels, which loads those too
KERNEL_MODULES = ("fusion.tracking", "fusion.wire", "fusion.frames", "fusion.geometry", "fusion.lane_match",
                  "sim.occlusion", "sim.world", "obu_service.admission", "obu_service.clock_envelope", "schemas.bit_rows")


def load_kernels() -> float:
    """Load (or compile) every kernel of ``KERNEL_MODULES`` and of every module imported before the call;
    seconds taken."""
    for name in KERNEL_MODULES:
        importlib.import_module(name)
    t0 = time.perf_counter()
    preload_scipy_blas()
    for k in Kernel._all:
        k.load()
    return time.perf_counter() - t0


# numba's first kernel load checks that BLAS and LAPACK are there by importing these two Cython modules
# (numba.np.linalg.ensure_blas / ensure_lapack); no kernel here calls them
SCIPY_BLAS_MODULES = ("scipy.linalg.cython_blas", "scipy.linalg.cython_lapack")


def preload_scipy_blas() -> list[str]:
    """Import scipy's ``cython_blas`` and ``cython_lapack`` extension modules from their files,
    without running the ``scipy.linalg`` package they live in; the names loaded so (none when
    scipy.linalg is already imported, or a file is not where scipy puts it: numba then imports
    them as usual).

    Importing a submodule runs its package's ``__init__`` first: for scipy.linalg that is its
    decompositions and scipy's array-API layer, 0.13-0.17 s of a service's start-up (a third of
    ``load_kernels``; ``benchmarks/cli_start.py``), for two modules that need none of it. Both are in
    ``sys.modules`` under their own names, so numba (and scipy itself, when something imports
    scipy.linalg later) finds the very same modules there.
    """
    if "scipy.linalg" in sys.modules:
        return []
    import scipy

    folder = Path(scipy.__file__).parent / "linalg"
    loaded = []
    for name in SCIPY_BLAS_MODULES:
        if name in sys.modules:
            continue
        files = [folder / (name.rsplit(".", 1)[1] + suffix) for suffix in importlib.machinery.EXTENSION_SUFFIXES]
        path = next((f for f in files if f.is_file()), None)
        if path is None:
            return loaded
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        try:
            spec.loader.exec_module(module)
        except BaseException:
            del sys.modules[name]
            raise
        loaded.append(name)
    return loaded
