"""`v2i eval` speed of the working tree against a git revision, alternating runs in one session
(so load from anything else hits both alike), and whether their reports are identical.

    python benchmarks/eval_ab.py --base REV [--scenarios a,b] [--rounds 3] [--seed 1] [--check-json]

The revision's ``src/`` and ``benchmarks/`` are extracted (``git archive``) into a temporary
directory. Each round runs ``benchmarks/eval_speed.py --repeats 1`` once per scenario and tree
(``PYTHONPATH=<tree>/src``), base first in even rounds, head first in odd ones; one line per
scenario: median x real time of each, head / base, and the runs; then the median ``import_s`` of
each tree (imports and compiled kernels, paid once per ``v2i eval`` process, outside x real
time: what a single short run feels on top of it; both trees' kernels are compiled before the
first run). ``--check-json`` compares
``v2i eval --scenario S --seed 0 --json -`` of both trees, byte for byte.
"""

from __future__ import annotations

import argparse
import io
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

HEAD = Path(__file__).resolve().parents[1]
CLI = "import sys; from v2i.cli import main; sys.exit(main(sys.argv[1:]))"


def extract(rev: str, into: Path) -> Path:
    """The revision's src/ and benchmarks/ under ``into``."""
    data = subprocess.run(["git", "-C", str(HEAD), "archive", rev, "src", "benchmarks"], capture_output=True,
                          check=True).stdout
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        tar.extractall(into, filter="data")
    return into


def isolate(base: Path) -> None:
    """The base tree must not see this tree's ``src/`` (on ``sys.path`` through the editable install):
    a package with an ``__init__`` there would win over the base's namespace package of the same name.
    ``base/sitecustomize.py`` takes it off ``sys.path`` in every base process."""
    (base / "sitecustomize.py").write_text(f"import sys\nsys.path[:] = [p for p in sys.path if p != {str(HEAD / 'src')!r}]\n")


def _run(tree: Path, args: list[str]) -> str:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tree / "src")] + ([] if tree == HEAD else [str(tree)])))
    out = subprocess.run([sys.executable, *args], env=env, capture_output=True, text=True, cwd=tree)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(args[:2])} failed in {tree}:\n{out.stderr[-2000:]}")
    return out.stdout


def x_real(tree: Path, scenario: str, seed: int) -> tuple[float, float]:
    """Simulated / wall seconds of one run of the scenario in that tree, and its process's import_s."""
    text = _run(tree, [str(tree / "benchmarks" / "eval_speed.py"), "--scenarios", scenario, "--repeats", "1",
                       "--seed", str(seed)])
    x, start_s = None, None
    for line in text.splitlines():
        parts = line.split()
        if parts and parts[0] == scenario:
            x = float(parts[3])
        elif parts and parts[0] == "import_s":
            start_s = float(parts[1])
    if x is None or start_s is None:
        raise RuntimeError(f"no line for {scenario} or import_s in:\n{text}")
    return x, start_s


def report(tree: Path, scenario: str) -> str:
    return _run(tree, ["-c", CLI, "eval", "--scenario", scenario, "--seed", "0", "--json", "-"])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", required=True, help="git revision to compare with (e.g. main~5, a commit)")
    ap.add_argument("--scenarios", default="connected-intersection,dense-intersection,highway-merge,"
                    "red-light-runner,roif-intersection,two-rsu-corridor", help="comma-separated")
    ap.add_argument("--rounds", type=int, default=3, help="runs of each tree per scenario (median)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--check-json", action="store_true", help="also compare the seed-0 reports byte for byte")
    args = ap.parse_args(argv)
    names = args.scenarios.split(",")
    with tempfile.TemporaryDirectory(prefix="v2i-eval-ab-") as tmp:
        base = extract(args.base, Path(tmp))
        isolate(base)
        for tree in (base, HEAD):  # a fresh extract compiles its kernels once, here, not in a timed import_s
            _run(tree, ["-c", CLI, "warm"])  # every kernel, through the command both trees have
        runs: dict[tuple[str, str], list[float]] = {(t, s): [] for t in ("base", "head") for s in names}
        start_s: dict[str, list[float]] = {"base": [], "head": []}
        for r in range(args.rounds):
            for s in names:
                trees = [("base", base), ("head", HEAD)]
                for label, tree in trees if r % 2 == 0 else trees[::-1]:
                    x, seconds = x_real(tree, s, args.seed)
                    runs[label, s].append(x)
                    start_s[label].append(seconds)
        if args.rounds:
            print(f"{'scenario':26s} {'base x':>7s} {'head x':>7s} {'ratio':>6s}  (median of {args.rounds}, "
                  f"seed {args.seed}, base {args.base})")
        for s in names if args.rounds else ():
            b, h = statistics.median(runs["base", s]), statistics.median(runs["head", s])
            print(f"{s:26s} {b:7.1f} {h:7.1f} {h / b:6.2f}  base {runs['base', s]} head {runs['head', s]}")
        if args.rounds:
            b, h = statistics.median(start_s["base"]), statistics.median(start_s["head"])
            print(f"{'import_s (per process)':26s} {b:7.2f} {h:7.2f} {h / b:6.2f}  (median of {len(start_s['head'])})")
        same = True
        for s in names if args.check_json else ():
            equal = report(base, s) == report(HEAD, s)
            same &= equal
            print(f"report {s} (seed 0): {'identical' if equal else 'DIFFERENT'}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
