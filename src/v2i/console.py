"""What the commands say and check at the console: a report's summary and JSON, a live run's exit code,
the files written, output paths checked before a long run.

Shared by ``v2i.cli`` and the command modules it runs (``v2i.replay``, ...), which must not import the
CLI itself (nothing imports ``v2i.cli``). Standard library only at import, so that ``v2i --help``
stays light.
"""

from __future__ import annotations

import json
import signal
import sys
from pathlib import Path


def emit(report: dict, json_path: str | None, summary=None) -> None:
    """Human summary (stderr when the JSON goes to stdout; default ``v2i.offline.spec.summary``) and
    the JSON report."""
    if summary is None:
        from v2i.offline.spec import summary

    print(summary(report), file=sys.stderr if json_path == "-" else sys.stdout)
    if json_path == "-":
        print(json.dumps(report, indent=2))
    elif json_path:
        Path(json_path).write_text(json.dumps(report, indent=2) + "\n")


def check_writable(path: Path, flag: str) -> None:
    """ValueError unless ``path`` names a file that can be created or replaced."""
    if path.is_dir():
        raise ValueError(f"{flag} {path} is a directory, not a file")
    if not path.parent.is_dir():
        raise ValueError(f"{flag} {path}: folder {path.parent} does not exist")


def check_folder(path: Path, flag: str) -> None:
    """ValueError unless ``path`` is a folder or can be made one (its nearest existing ancestor is one)."""
    existing = next(p for p in (path, *path.parents) if p.exists())
    if not existing.is_dir():
        raise ValueError(f"{flag} {path}: {existing} is a file, not a folder")


def wrote(paths: list[Path], prog: str) -> None:
    print(f"{prog}: wrote {', '.join(str(p) for p in paths)}", file=sys.stderr)


def live(run, prog: str) -> dict | int:
    """The report of a live run (services as processes), or its exit code: 1 when it failed,
    130 when interrupted (SIGINT or SIGTERM); the run stops its services either way."""
    from v2i.orchestration.demo import DemoError

    interrupt_on(signal.SIGINT, signal.SIGTERM)
    try:
        return run()
    except DemoError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; all services stopped", file=sys.stderr)
        return 130


def interrupt_on(*signals: int) -> None:
    """Turn these signals into KeyboardInterrupt, even where a parent shell ignored them."""

    def _raise(signum, frame):
        raise KeyboardInterrupt

    for sig in signals:
        signal.signal(sig, _raise)
