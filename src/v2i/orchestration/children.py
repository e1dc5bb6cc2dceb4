"""The service processes an orchestrator starts, and the start handshake with them.

A ``Child`` is one service process (``v2i rsu`` / ``obu`` / ``link`` / ``world`` ...). A thread
reads its stdout JSON lines (``ready``, and ``started`` from a service run with ``--await-start``;
every one also goes to ``events``); another relays its stderr lines whole to this process's
stderr (so that a live status line, ``v2i.telemetry.live_line``, keeps them above it), each prefixed
with the child's label (``[obu ego]``) unless the service already named itself so, the last
``STDERR_LINES_KEPT`` kept for error messages. Its stdin is a pipe for the start line.

The handshake (``v2i.runtime.process``), for children started with ``--await-start``::

    children = {"rsu": Child("rsu", [..., "--await-start"], label="rsu rsu1"), ...}
    ready_s = wait_ready(children.values(), progress="v2i demo")  # one bound for all, a progress line
    ...  # open the monitor sessions, subscribe
    start_ns = start_all(children.values())  # now + START_LEAD_S, sent to every child

A child started without ``--await-start`` (the link emulator) ignores the line. Only the
processes started here are ever signalled, by pid.
"""

from __future__ import annotations

import collections
import json
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterable

from v2i.runtime.process import start_line
from v2i.telemetry.live_line import StatusLine

READY_TIMEOUT_S = 120.0  # every child must be ready within this (a cold start on a busy 2-core machine: ~10 s)
# time zero this far after the start line is sent: the OBU's clock sync queries the RSU from 1 s before
# time zero (v2i.clock.time_requests.SYNC_LEAD_NS), plus the line's delivery and the services' _begin
START_LEAD_S = 1.5
STDERR_LINES_KEPT = 12  # a child's last stderr lines, shown when it dies or is not ready
POLL_S = 0.05  # how often wait_ready looks at each child


class DemoError(RuntimeError):
    """A run that could not go on: a child died, or was not ready in time."""


class Child:
    """One service process; ``name`` is how the orchestrator calls it (``rsu``, ``obu car-2``),
    ``label`` how its relayed stderr lines are prefixed (default ``name``)."""

    def __init__(self, name: str, argv: list[str], label: str | None = None):
        self.name, self.argv, self.label = name, argv, label or name
        self.ahead_ms: float | None = None  # from its "started" line: ms it began before time zero
        self.stderr_tail: collections.deque[str] = collections.deque(maxlen=STDERR_LINES_KEPT)  # last stderr lines
        self.events: queue.Queue[dict] = queue.Queue()  # every JSON object it printed on stdout, in order
        self._ready = threading.Event()
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, bufsize=1, start_new_session=True)
        self._stdout = threading.Thread(target=self._read_stdout, name=f"{self.name}-stdout", daemon=True)
        self._stderr = threading.Thread(target=self._relay_stderr, name=f"{self.name}-stderr", daemon=True)
        self._stdout.start()
        self._stderr.start()

    @property
    def ready(self) -> bool:
        return self._ready.is_set()

    def _read_stdout(self) -> None:
        for line in self.proc.stdout:
            try:
                event = json.loads(line)
            except ValueError:
                continue
            if not isinstance(event, dict):
                continue
            self.events.put(event)
            if event.get("event") == "ready":
                self._ready.set()
            elif event.get("event") == "started" and isinstance(event.get("ahead_ms"), (int, float)):
                self.ahead_ms = float(event["ahead_ms"])

    def _relay_stderr(self) -> None:
        """Each stderr line whole to this process's stderr (looked up per line: a live line may wrap it)."""
        prefix = f"[{self.label}]"
        for line in self.proc.stderr:
            line = line.rstrip("\n")
            if not line.startswith(prefix):
                line = f"{prefix} {line}"
            self.stderr_tail.append(line)
            try:
                sys.stderr.write(line + "\n")
                sys.stderr.flush()
            except (OSError, ValueError):  # our stderr closed (interpreter exit): keep draining the pipe
                pass

    def tail(self) -> str:
        """Its last stderr lines, indented, for an error message ("" when it wrote none)."""
        self._stderr.join(0.5)  # a child that just exited: its last lines are still being read
        return "".join(f"\n    {line}" for line in self.stderr_tail)

    def poll_ready(self, timeout_s: float = 0.0) -> bool:
        """True once the child printed its ready line; waits at most ``timeout_s`` for it. DemoError
        (with its last stderr lines) when it exited before."""
        if self._ready.wait(timeout_s) if timeout_s > 0 else self._ready.is_set():
            return True
        if self.proc.poll() is not None:
            self._stdout.join(0.5)  # a ready line and the exit can come together
            if self.ready:
                return True
            raise DemoError(f"{self.name} exited with code {self.proc.returncode} before it was ready{self.tail()}")
        return False

    def start(self, start_ns: int) -> None:
        """Send the start line (time zero ``start_ns``, Unix ns) and close stdin; a child that already
        exited is left to the caller's checks."""
        try:
            self.proc.stdin.write(start_line(start_ns))
            self.proc.stdin.close()
        except (BrokenPipeError, OSError, ValueError):
            pass

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 5.0) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        for stream in (self.proc.stdin, self.proc.stdout):
            try:
                stream.close()
            except (OSError, ValueError):
                pass


def wait_ready(children: Iterable[Child], timeout_s: float = READY_TIMEOUT_S, progress: str | None = None) -> float:
    """Wait until every child printed its ready line; the seconds waited. ``progress``: a status line
    "PROGRESS: waiting for rsu, obu (3.2 s)" on stderr meanwhile (None: none). DemoError naming the
    child that died, or every child not ready after ``timeout_s``, with their last stderr lines."""
    children = list(children)
    t0 = time.monotonic()
    waiting = lambda: [c for c in children if not c.ready]  # noqa: E731
    line = None
    if progress:
        line = StatusLine(lambda: f"{progress}: waiting for {', '.join(c.name for c in waiting()) or 'nothing'} "
                                  f"({time.monotonic() - t0:.1f} s)")
        line.start()
    try:
        while late := waiting():
            elapsed_s = time.monotonic() - t0
            if elapsed_s >= timeout_s:
                raise DemoError(f"not ready after {timeout_s:g} s (--ready-timeout): "
                                + "; ".join(f"{c.name}{c.tail()}" for c in late))
            late[0].poll_ready(min(POLL_S, timeout_s - elapsed_s))
            for child in late[1:]:
                child.poll_ready()
    finally:
        if line is not None:
            line.stop()
    return time.monotonic() - t0


def start_all(children: Iterable[Child], start_ns: int | None = None, lead_s: float = START_LEAD_S) -> int:
    """Send every child the start line; time zero ``start_ns`` (default: now + ``lead_s``), returned."""
    start_ns = time.time_ns() + round(lead_s * 1e9) if start_ns is None else start_ns
    for child in children:
        child.start(start_ns)
    return start_ns


def ahead_ms(children: Iterable[Child]) -> dict[str, float | None]:
    """How many ms before time zero each child began (its "started" line; None: it said none)."""
    return {c.name: c.ahead_ms for c in children}
