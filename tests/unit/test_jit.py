"""v2i.core.jit: kernels compile for their declared argument types only, take read-only and strided
inputs, refuse other dtypes, and load_kernels loads every kernel of the tracker."""

import numpy as np
import pytest

from v2i.fusion import kalman
from v2i.core.jit import Kernel, load_kernels
from v2i.offline.kernels import ALL_KERNEL_MODULES, RUN_KERNEL_MODULES


def test_load_kernels_loads_every_kernel():
    load_kernels(RUN_KERNEL_MODULES)
    names = {k.fn.__module__ + "." + k.fn.__name__ for k in Kernel._all}
    assert {"v2i.fusion.kalman.update_rows", "v2i.fusion.gating._gate_single_pairs", "v2i.fusion.association._split",
            "v2i.fusion.covariance_intersection.ci_fuse_objects", "v2i.sim.occlusion._blocked"} <= names
    for k in Kernel._all:
        assert k.load().signatures == [k.argument_types]  # one compiled signature, no other


def test_a_kernel_takes_read_only_and_strided_inputs_and_refuses_other_dtypes():
    rng = np.random.default_rng(0)
    x, p = rng.normal(size=(5, 4)), np.tile(np.eye(4), (5, 1, 1))
    z, r = rng.normal(size=(3, 4))[:, ::2], np.tile(np.eye(2), (3, 1, 1))  # strided measurements
    r.flags.writeable = False
    rows, cols = np.array([4, 0, 2]), np.arange(3)
    x_ref, p_ref, _ = kalman.update(x[rows], p[rows], np.ascontiguousarray(z), r)
    kalman.update_rows(x, p, rows, z, r, cols, 0)
    np.testing.assert_array_equal(x[rows], x_ref)
    np.testing.assert_array_equal(p[rows], p_ref)
    assert np.all(p[[1, 3]] == np.eye(4))  # rows not named are not touched
    with pytest.raises(TypeError):
        kalman.update_rows(x, p, rows, z.astype(np.float32), r, cols, 0)
    with pytest.raises(TypeError):  # an output must be writable
        x.flags.writeable = False
        kalman.update_rows(x, p, rows, z, r, cols, 0)


def test_a_division_by_zero_in_a_kernel_gives_nan_as_numpy_does():
    """A zero innovation covariance (a zero track and measurement covariance): NaN, not ZeroDivisionError."""
    x, p = np.zeros((1, 4)), np.zeros((1, 4, 4))
    kalman.update_rows(x, p, np.array([0]), np.zeros((1, 2)), np.zeros((1, 2, 2)), np.array([0]), 0)
    assert np.isnan(x).all() and np.isnan(p[0, :2, :2]).all()


def test_load_kernels_loads_the_simulator_and_every_kernel_imported_before():
    """v2i.sim.world's body states are in RUN_KERNEL_MODULES (a simulated run's); a kernel of a module imported before
    the call (the evaluation's matching, imported by the offline evaluator) is loaded too."""
    import importlib

    assert "v2i.sim.world" in RUN_KERNEL_MODULES
    importlib.import_module("v2i.scoring.detection_metrics")
    load_kernels(RUN_KERNEL_MODULES)
    loaded = {k.fn.__module__ + "." + k.fn.__name__ for k in Kernel._all if k._compiled is not None}
    assert {"v2i.sim.world._states", "v2i.scoring.detection_metrics._frame_flags"} <= loaded


def test_kernel_modules_name_every_module_a_service_runs_kernels_of():
    """Every module under src/ that declares a kernel, but the offline evaluation's, is loaded by
    load_kernels(RUN_KERNEL_MODULES) alone (a fresh interpreter): otherwise a service would compile or load that
    kernel at its first call, mid-run; with the evaluation's (ALL_KERNEL_MODULES, v2i warm's), every one."""
    import subprocess
    import sys
    from pathlib import Path

    src = Path(__file__).resolve().parents[2] / "src"
    declared = {str(p.relative_to(src).with_suffix("")).replace("/", ".") for p in src.rglob("*.py")
                if "@kernel(" in p.read_text()}
    code = ("from v2i.core.jit import Kernel, load_kernels; from v2i.offline.kernels import RUN_KERNEL_MODULES; "
            "load_kernels(RUN_KERNEL_MODULES); "
            "print(' '.join(sorted({k.fn.__module__ for k in Kernel._all if k._compiled is not None})))")
    loaded = set(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split())
    evaluation = set(ALL_KERNEL_MODULES) - set(RUN_KERNEL_MODULES)
    assert evaluation == {"v2i.scoring.detection_metrics"} and declared - evaluation <= loaded


@pytest.mark.parametrize("service", ["rsu_service", "obu_service"])
def test_a_service_loads_its_own_kernels_and_no_simulator(service):
    """``load_kernels(KERNEL_MODULES)`` with the service's own list, as its node calls it (a fresh interpreter):
    its kernels, no module of the simulator (a service on a site file runs none); with the simulator's modules,
    every kernel a run needs."""
    import subprocess
    import sys

    import obu_service
    import rsu_service
    from v2i import sim

    assert set(RUN_KERNEL_MODULES) == {*rsu_service.KERNEL_MODULES, *obu_service.KERNEL_MODULES, *sim.KERNEL_MODULES}
    code = (f"import sys; from {service} import KERNEL_MODULES; from v2i.core.jit import load_kernels; "
            "load_kernels(KERNEL_MODULES); print(sorted(m for m in sys.modules if m.startswith('v2i.sim')))")
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split() == ["[]"]


def test_load_kernels_reaches_scipys_blas_modules_without_importing_scipy_linalg():
    """load_kernels loads scipy's cython_blas / cython_lapack from their files (v2i.core.jit.preload_scipy_blas), not
    through scipy.linalg's package (a tenth of a second of a service's start); scipy.linalg imported afterwards works
    and finds those very modules, and numba's BLAS and LAPACK still serve a kernel (a fresh interpreter)."""
    import subprocess
    import sys

    code = """
import sys
import numpy as np
from v2i.core.jit import SCIPY_BLAS_MODULES, load_kernels
from v2i.offline.kernels import RUN_KERNEL_MODULES
load_kernels(RUN_KERNEL_MODULES)
assert "scipy.linalg" not in sys.modules, "load_kernels imported scipy.linalg"
preloaded = [sys.modules[name] for name in SCIPY_BLAS_MODULES]
import numba
import scipy.linalg
from scipy.linalg import cython_blas, cython_lapack
from scipy.optimize import linear_sum_assignment
assert [cython_blas, cython_lapack] == preloaded
assert np.allclose(scipy.linalg.inv(4 * np.eye(3)), 0.25 * np.eye(3))
assert linear_sum_assignment(np.array([[4, 1, 3], [2, 0, 5], [3, 2, 2]]))[1].tolist() == [1, 0, 2]
solve = numba.njit(lambda a, b: (np.dot(a, b), np.linalg.inv(a)))
product, inverse = solve(2 * np.eye(2), np.ones((2, 2)))
assert np.allclose(product, 2) and np.allclose(inverse, 0.5 * np.eye(2))
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_preloading_scipys_blas_modules_is_skipped_once_scipy_linalg_is_imported():
    import scipy.linalg  # noqa: F401  (this test process: the package is there, its modules are its own)

    from v2i.core.jit import preload_scipy_blas

    assert preload_scipy_blas() == []


class _Stream:
    """A stderr stand-in: what was written, and whether it is a terminal."""

    def __init__(self, tty: bool):
        self.text, self.tty = "", tty

    def write(self, text: str) -> None:
        self.text += text

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return self.tty


def test_compile_progress_prints_at_the_first_compile_then_a_line_every_ten_seconds_and_a_closing_line():
    from v2i.core.jit import CompileProgress

    now = [100.0]
    stream = _Stream(tty=False)
    progress = CompileProgress(3, "/cache", stream, clock=lambda: now[0])
    progress.loaded()  # loaded from the cache: nothing said
    assert stream.text == ""
    progress.on_start(None)
    assert stream.text == "v2i: compiling numba kernels 1/3 (once per machine; cached in /cache)\n"
    now[0] += 9.0
    progress.loaded()  # 9 s after the last line: no new line
    assert stream.text.count("\n") == 1
    progress.on_start(None)
    now[0] += 1.5
    progress.loaded()
    progress.finish()
    assert stream.text.splitlines()[1:] == ["v2i: compiling numba kernels 3/3 (once per machine; cached in /cache)",
                                           "v2i: compiled 2 numba kernels in 10.5 s (once per machine; cached in /cache)"]


def test_compile_progress_rewrites_one_line_on_a_terminal_and_says_nothing_without_a_compile():
    from v2i.core.jit import CompileProgress

    stream = _Stream(tty=True)
    progress = CompileProgress(2, "/cache", stream)
    progress.on_start(None)
    progress.loaded()
    progress.loaded()
    progress.finish()
    lines = stream.text.split("\r\x1b[K")[1:]
    assert [line.split(" (")[0] for line in lines] == ["v2i: compiling numba kernels 0/2",
                                                       "v2i: compiling numba kernels 1/2",
                                                       "v2i: compiling numba kernels 2/2",
                                                       "v2i: compiled 1 numba kernels in 0.0 s"]
    assert stream.text.count("\n") == 1 and stream.text.endswith("\n")
    quiet = _Stream(tty=True)
    warm = CompileProgress(2, "/cache", quiet)
    warm.loaded()
    warm.loaded()
    warm.finish()
    assert quiet.text == ""


def test_a_cold_compile_says_so_on_stderr_and_a_cached_load_says_nothing(tmp_path):
    """A kernel module of its own, compiled into an empty NUMBA_CACHE_DIR in a fresh interpreter: the progress
    and closing lines; the same load again (from the cache): no output at all."""
    import os
    import subprocess
    import sys

    (tmp_path / "tiny_kernels.py").write_text(
        "from v2i.core.jit import I64, kernel\n\n\n@kernel(I64)\ndef plus_one(x):\n    return x + 1\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
           "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    code = ("import tiny_kernels; from v2i.core.jit import Kernel, load_each; "
            "print(load_each([k for k in Kernel._all if k.fn.__module__ == 'tiny_kernels']), tiny_kernels.plus_one(2))")
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
            for _ in range(2)]
    assert runs[0].stdout.split() == ["1", "3"]
    first, *_, last = runs[0].stderr.splitlines()
    assert first.startswith(f"v2i: compiling numba kernels 0/1 (once per machine; cached in {tmp_path / 'cache'}")
    assert last.startswith("v2i: compiled 1 numba kernels in ")
    assert runs[1].stdout.split() == ["0", "3"] and runs[1].stderr == ""


def test_v2i_warm_loads_every_kernel_and_says_how_long_and_where():
    import subprocess
    import sys

    load_kernels(ALL_KERNEL_MODULES)  # every module that declares a kernel (the test above checks the list)
    out = subprocess.run([sys.executable, "-m", "v2i", "warm", "--check"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr  # --check: all of them came from the cache
    line = out.stdout.strip()
    assert line.startswith(f"v2i warm: {len(Kernel._all)} numba kernels ready (0 compiled) in ") and "; cached in " in line


def test_v2i_warm_check_fails_when_a_kernel_had_to_compile(tmp_path):
    import os
    import subprocess
    import sys

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    code = "import v2i.offline.kernels as k; k.ALL_KERNEL_MODULES = ('v2i.fusion.wire',); " \
           "from v2i.cli import main; raise SystemExit(main(['warm', '--check']))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 1 and "compiled) in " in out.stdout and "(0 compiled)" not in out.stdout, out.stderr


def test_kernels_of_two_modules_compile_in_two_worker_processes(tmp_path):
    """Two kernel modules, an empty cache and two workers (a fresh interpreter): each module's kernel compiles
    in a worker process and this process loads both from the cache (numba's cache hits, no miss here); the
    progress says so and counts both."""
    import os
    import subprocess
    import sys

    for name, body in (("tiny_a", "x + 1"), ("tiny_b", "x * 3")):
        (tmp_path / f"{name}.py").write_text(f"from v2i.core.jit import I64, kernel\n\n\n@kernel(I64)\ndef f(x):\n"
                                            f"    return {body}\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
           "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    code = ("import tiny_a, tiny_b; from v2i.core.jit import Kernel, load_each; "
            "mine = [k for k in Kernel._all if k.fn.__module__.startswith('tiny_')]; "
            "print(load_each(mine, workers=2), tiny_a.f(2), tiny_b.f(2), "
            "[(sum(k._compiled.stats.cache_hits.values()), sum(k._compiled.stats.cache_misses.values())) for k in mine])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "2 3 6 [(1, 0), (1, 0)]"
    lines = out.stderr.splitlines()
    assert lines[0].startswith("v2i: compiling numba kernels 0/2 (once per machine, 2 processes; cached in ")
    assert lines[-1].startswith("v2i: compiled 2 numba kernels in ")


def test_compile_groups_keep_a_module_whole_and_balance_the_source():
    from v2i.core.jit import _groups, _jitted_size

    load_kernels(RUN_KERNEL_MODULES)
    groups = _groups(Kernel._all, 2)
    modules = [{k.fn.__module__ for k in g} for g in groups]
    assert len(groups) == 2 and not modules[0] & modules[1]  # no module in both
    assert sorted(k for g in groups for k in map(id, g)) == sorted(map(id, Kernel._all))
    import sys

    sizes = [sum(_jitted_size(sys.modules[m]) for m in ms) for ms in modules]
    assert max(sizes) < 0.7 * sum(sizes)  # the largest module (the clock fit) does not take all
    assert len(_groups(Kernel._all, 1)) == 1 and sorted(map(id, _groups(Kernel._all, 1)[0])) == sorted(map(id, Kernel._all))


def test_kernels_compile_here_when_the_worker_processes_fail(tmp_path):
    import os
    import subprocess
    import sys

    for name in ("tiny_c", "tiny_d"):
        (tmp_path / f"{name}.py").write_text("from v2i.core.jit import I64, kernel\n\n\n@kernel(I64)\ndef f(x):\n"
                                            "    return x - 1\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
           "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    code = ("import tiny_c, tiny_d; import v2i.core.jit as j; j._WORKER = 'import sys; sys.exit(3)'; "
            "mine = [k for k in j.Kernel._all if k.fn.__module__.startswith('tiny_')]; "
            "print(j.load_each(mine, workers=2), tiny_c.f(2), tiny_d.f(5), "
            "[sum(k._compiled.stats.cache_misses.values()) for k in mine])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0 and out.stdout.strip() == "2 1 4 [1, 1]", out.stderr
