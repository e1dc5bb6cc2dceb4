"""Compiled kernels (numba): 18 of them, for the tracker's per-pair loops, the OBU's clock fit, the
simulator's line of sight and body states, the rotated-box IoU, the codec's section packing and
quantising, the fitting of objects to the wire, lane matching and the evaluation's per-frame
detection matching.

A kernel stays only where it saves at least ~1 % of a cycle (``benchmarks/cycle_compute.py``) or
of a whole ``v2i eval`` of some bundled scenario against its plain numpy / scipy / shapely
reference, which lives beside it in ``src/`` with a test holding the two equal. The tracker updates
a few hundred tracks with lists of a few to a few hundred objects, ten times a second per source:
numpy's fixed cost per call was the whole cost, so gating, association's bookkeeping, the Kalman
updates, covariance intersection and the matched tracks' bookkeeping are loops over the pairs
(each several times faster than its numpy form on the recorded calls). So are the clock fit of
``v2i.clock.clock_envelope`` (~26 against ~690 us per fit), ``v2i.sim.occlusion``'s line of sight,
``v2i.sim.world``'s body states, ``v2i.scoring.detection_metrics``' matches per frame, ``v2i.fusion.geometry``'s
IoU, ``v2i.fusion.lane_match`` and ``schemas.bit_rows``. The commits that removed the others (scipy's
own assignment solver, the codec's unpacking, one-line checks) give their measurements.

``kernel(*argument_types)`` compiles a function for exactly those argument types (and no others)
at its first call, or when ``load_kernels`` loads the kernels of the modules its caller names: the
services and the offline evaluator do that before they start, so that no cycle ever waits for the
compiler. The machine
code is cached under ``__pycache__`` (or the user's cache directory where the package is not
writable): compiled once per machine (``v2i warm`` does it ahead), then loaded in ~0.35-0.45 s
per process (most of it numba's own set-up at the first load; its check for BLAS and LAPACK
reaches scipy's two Cython modules directly: ``preload_scipy_blas``). A compile says so on stderr
within a second (``CompileProgress``), and the kernels not in the cache compile in one worker
process per core, whole modules each (``compile_apart``): ~28 s on a 2-core machine at load ~2
for all 18 (the 30 before took ~46 s on a quiet one). Inputs are declared read-only arrays of
any layout (``IN_*``: writable and strided arrays convert to them), the arrays a kernel writes
``OUT_*``; an array of another dtype is a ``TypeError`` (callers pass float64 and int64).
``helper`` is for the functions the kernels call (compiled into them). numba checks a cached
kernel against its own source file only: the helpers a kernel calls live in its module, and
after a change to ``OPTIONS`` here the cached files (``__pycache__/*.nbi``, ``*.nbc``) must be
deleted. Kernels are loops, not numpy's array expressions, sorts or quantiles where they can be:
each of those adds ~0.1-1 s to a compile; and a helper called with an int constant compiles for
that literal value (pass a float or a variable), once per constant.
"""
from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import inspect
import os
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterable, TextIO

from numba import njit, types
from numba.core import event

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
        self._dispatcher: Callable | None = None
        Kernel._all.append(self)

    def __call__(self, *args):
        return (self._compiled or self.load())(*args)

    def load(self) -> Callable:
        """The compiled function (loaded from the cache, or compiled and cached, with ``CompileProgress``)."""
        if self._compiled is None:
            load_each([self])
        return self._compiled

    def cache_dir(self) -> str:
        """The folder numba caches this kernel's machine code in."""
        return self._lazy_dispatcher()._cache._cache_path

    def _lazy_dispatcher(self):
        if self._dispatcher is None:
            self._dispatcher = njit(**OPTIONS)(self.fn)
        return self._dispatcher

    def _compile(self) -> None:
        """What ``njit(argument_types, ...)`` does: compile (or load) that signature, then no other."""
        dispatcher = self._lazy_dispatcher()
        dispatcher.compile(self.argument_types)
        dispatcher.disable_compile()
        self._compiled = dispatcher


def kernel(*argument_types) -> Callable[[Callable], Kernel]:
    """Decorator: the function as a ``Kernel`` for these argument types."""
    return lambda fn: Kernel(fn, argument_types)


def load_kernels(modules: Iterable[str] = ()) -> float:
    """Load (or compile) every kernel of ``modules`` (imported here) and of every module imported before
    the call; seconds taken. The caller names the modules whose kernels it will run, the core none above
    it: each package lists the modules of its process (``rsu_service.KERNEL_MODULES``,
    ``obu_service.KERNEL_MODULES``), or of its own kernels (``v2i.sim.KERNEL_MODULES``,
    ``v2i.scoring.KERNEL_MODULES``); ``v2i.offline.kernels`` those of a whole run. A compile shows its
    progress on stderr (``CompileProgress``)."""
    for name in modules:
        importlib.import_module(name)
    t0 = time.perf_counter()
    preload_scipy_blas()
    load_each(Kernel._all)
    return time.perf_counter() - t0


def warm(modules: Iterable[str]) -> tuple[str, int]:
    """``v2i warm``: load or compile every kernel of ``modules`` (the command names them all: the services'
    and the offline evaluator's) ahead of any run (a compile shows its progress); the closing line (how
    many, the seconds taken, the cache) and how many of them compiled."""
    t0 = time.perf_counter()
    for name in modules:
        importlib.import_module(name)
    preload_scipy_blas()
    compiled = load_each(Kernel._all)
    return (f"v2i warm: {len(Kernel._all)} numba kernels ready ({compiled} compiled) in "
            f"{time.perf_counter() - t0:.1f} s; cached in {cache_location([k.cache_dir() for k in Kernel._all])}",
            compiled)


def load_each(kernels: list[Kernel], stream: TextIO | None = None, workers: int | None = None) -> int:
    """Load (or compile) these kernels; how many of them compiled. Nothing is printed unless one compiles.
    Those not in the cache are compiled first by ``workers`` processes at once (default: one per core, at
    most ``MAX_WORKERS``; ``compile_apart``), then all of them load here."""
    pending = [k for k in kernels if k._compiled is None]
    if not pending:
        return 0
    progress = CompileProgress(len(pending), cache_location([k.cache_dir() for k in pending]),
                               sys.stderr if stream is None else stream)
    missing = [k for k in pending if in_cache(k) is False]
    apart = compile_apart(missing, progress, _cores() if workers is None else workers)
    with event.install_listener("numba:compile", progress):
        for k in pending:
            k._compile()
            if k not in apart:
                progress.loaded()
    progress.finish()
    return progress.compiled


def in_cache(k: Kernel) -> bool | None:
    """Whether numba's cache holds k's machine code for this source (None: this numba cannot be asked;
    its ``Cache`` internals, as ``Dispatcher.compile`` reads them)."""
    try:
        dispatcher = k._lazy_dispatcher()
        dispatcher.targetctx.refresh()
        cache = dispatcher._cache
        return cache._index_key(k.argument_types, dispatcher.targetctx.codegen()) in cache._cache_file._load_index()
    except Exception:  # noqa: BLE001  (any other numba: the kernels compile here, one after the other)
        return None


MAX_WORKERS = 4
_WORKER = "import sys; from v2i.core.jit import compile_named; compile_named(sys.argv[1:])"


def compile_apart(kernels: list[Kernel], progress: CompileProgress, workers: int) -> set[Kernel]:
    """Compile these kernels into the cache in ``workers`` processes at once, the kernels of one module in one
    process (a kernel's helpers live in its module: no two processes write one cache index), and say so in
    ``progress``; the kernels they compiled. Nothing (they compile here) for one worker or one module."""
    groups = _groups(kernels, workers)
    if len(groups) < 2:
        return set()
    progress.started(len(groups))
    by_name = {_name(k): k for k in kernels}
    lines: queue.SimpleQueue = queue.SimpleQueue()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    procs = [subprocess.Popen([sys.executable, "-c", _WORKER, *map(_name, g)], stdout=subprocess.PIPE,
                              stderr=subprocess.DEVNULL, text=True, env=env) for g in groups]
    for proc in procs:
        threading.Thread(target=_pump, args=(proc.stdout, lines), daemon=True).start()
    done, running = set(), len(procs)
    while running:
        line = lines.get()
        if line is None:
            running -= 1
        elif by_name.get(line.strip()) is not None and by_name[line.strip()] not in done:
            done.add(by_name[line.strip()])
            progress.loaded(compiled=True)
    for proc in procs:
        proc.wait()
    return done


def compile_named(names: list[str]) -> None:
    """A worker of ``compile_apart``: compile the kernels ``module:name`` into the cache, a line per kernel done."""
    for name in names:
        module, _, fn = name.partition(":")
        importlib.import_module(module)
        kernel = next(k for k in Kernel._all if _name(k) == name)
        kernel._compile()
        print(name, flush=True)


def _name(k: Kernel) -> str:
    return f"{k.fn.__module__}:{k.fn.__qualname__}"


def _pump(stream: TextIO, lines: queue.SimpleQueue) -> None:
    for line in stream:
        lines.put(line)
    lines.put(None)


def _groups(kernels: list[Kernel], workers: int) -> list[list[Kernel]]:
    """The kernels in at most ``workers`` groups of whole modules, the larger modules (by the size of their
    compiled source, ``_jitted_size``: what a compile's time follows) first, each to the lightest group."""
    modules: dict[str, list[Kernel]] = {}
    for k in kernels:
        modules.setdefault(k.fn.__module__, []).append(k)
    size = {m: _jitted_size(sys.modules[m]) for m in modules}
    groups: list[list[Kernel]] = [[] for _ in range(max(1, min(workers, len(modules))))]
    weight = [0] * len(groups)
    for m in sorted(modules, key=lambda m: -size[m]):
        lightest = weight.index(min(weight))
        groups[lightest] += modules[m]
        weight[lightest] += size[m]
    return [g for g in groups if g]


def _jitted_size(module) -> int:
    """Characters of source of a module's kernels and helpers (numba dispatchers: their ``py_func``)."""
    functions = [obj.fn if isinstance(obj, Kernel) else getattr(obj, "py_func", None) for obj in vars(module).values()]
    return sum(len(inspect.getsource(f)) for f in functions
               if inspect.isfunction(f) and f.__module__ == module.__name__)


def _cores() -> int:
    """Worker processes for a compile: the cores this process may run on, at most MAX_WORKERS."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return min(cores, MAX_WORKERS)


def cache_location(folders: list[str]) -> str:
    """One name for the folders numba caches in: the folder, or where they all are."""
    unique = sorted(set(folders))
    if len(unique) == 1:
        return unique[0]
    common = os.path.commonpath(unique)
    if all(os.path.basename(f) == "__pycache__" for f in unique):
        return os.path.join(common, "*", "__pycache__")
    return common


class CompileProgress(event.Listener):
    """What a one-time compile says on stderr: numba's first ``numba:compile`` event (a cache miss of a
    kernel or of a helper it calls) prints the first line at once, then each kernel loaded updates it,
    rewritten in place on a terminal, elsewhere a plain line at most every ``LINE_EVERY_S``; a closing
    line with the time taken. A load from the cache fires no event and prints nothing."""

    LINE_EVERY_S = 10.0

    def __init__(self, total: int, cache: str, stream: TextIO, clock: Callable[[], float] = time.monotonic):
        self.total, self.cache, self.stream, self.clock = total, cache, stream, clock
        self.done = self.compiled = 0
        self._compiling = False  # a compile event since the last kernel loaded
        self._t0 = self._last_line = None
        self._tty = stream.isatty()
        self._where = ""

    def on_start(self, ev) -> None:
        self._compiling = True
        self.started()

    def on_end(self, ev) -> None:
        pass

    def started(self, processes: int = 1) -> None:
        """A compile begins (here, or in ``processes`` worker processes): the first line, once."""
        if processes > 1:
            self._where = f", {processes} processes"
        if self._t0 is None:
            self._t0 = self.clock()
            self._show()

    def loaded(self, compiled: bool = False) -> None:
        """One more kernel loaded, or compiled (here, or in a worker process: ``compiled``)."""
        self.done += 1
        self.compiled += self._compiling or compiled
        self._compiling = False
        if self._t0 is not None and (self._tty or self.clock() - self._last_line >= self.LINE_EVERY_S):
            self._show()

    def finish(self) -> None:
        if self._t0 is not None:
            self._write(f"v2i: compiled {self.compiled} numba kernels in {self.clock() - self._t0:.1f} s "
                        f"(once per machine; cached in {self.cache})", end="\n")

    def _show(self) -> None:
        self._last_line = self.clock()
        self._write(f"v2i: compiling numba kernels {self.done}/{self.total} (once per machine{self._where}; cached in "
                    f"{self.cache})", end="" if self._tty else "\n")

    def _write(self, text: str, end: str) -> None:
        self.stream.write(("\r\x1b[K" if self._tty else "") + text + end)
        self.stream.flush()


# numba's first kernel load checks that BLAS and LAPACK are there by importing these two Cython modules
# (numba.np.linalg.ensure_blas / ensure_lapack); no kernel here calls them
SCIPY_BLAS_MODULES = ("scipy.linalg.cython_blas", "scipy.linalg.cython_lapack")


def preload_scipy_blas() -> list[str]:
    """Import scipy's ``cython_blas`` and ``cython_lapack`` extension modules from their files
    (``import_extension``); the names loaded so (none when scipy.linalg is already imported, or a
    file is not where scipy puts it: numba then imports them as usual).

    Importing a submodule runs its package's ``__init__`` first: for scipy.linalg that is its
    decompositions and scipy's array-API layer, 0.13-0.17 s of a service's start-up (a third of
    ``load_kernels``; ``benchmarks/cli_start.py``), for two modules that need none of it.
    """
    if "scipy.linalg" in sys.modules:
        return []
    loaded = []
    for name in SCIPY_BLAS_MODULES:
        if name in sys.modules:
            continue
        if import_extension(name) is None:
            return loaded
        loaded.append(name)
    return loaded


def import_extension(name: str):
    """The extension module ``name`` (e.g. ``scipy.optimize._lsap``) loaded from its file beside its
    package's ``__init__`` without running that ``__init__`` (only the top-level package is imported); None
    where no such file is there. It is put in ``sys.modules`` under its own name, so that the package,
    when something imports it later, finds the very same module there."""
    if name in sys.modules:
        return sys.modules[name]
    top, *middle, leaf = name.split(".")
    folder = Path(importlib.import_module(top).__file__).parent.joinpath(*middle)  # (scipy's own __init__ is light)
    files = [folder / (leaf + suffix) for suffix in importlib.machinery.EXTENSION_SUFFIXES]
    path = next((f for f in files if f.is_file()), None)
    if path is None:
        return None
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module
