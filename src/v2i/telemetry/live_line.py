"""The compact live line of ``v2i demo`` / ``v2i chaos run``: progress, misses, mode, on stderr.

``StatusLine``: one line on stderr that a thread redraws every ``REFRESH_S`` from a text
function. On a terminal the line is rewritten in place (``\\r``, cut to the terminal's width)
and every other stderr line of this process (the demo's log, its children's lines relayed by
``v2i.orchestration.children``) is printed whole above it, never cut by it nor mixed with another
thread's; elsewhere (a file, a pipe, CI) a plain line every ``PLAIN_EVERY_S``. stdout is never
touched, so ``--json -`` stays clean. The demo shows one while it waits for its services
("waiting for rsu, obu (3.2 s)"), then the ``LiveLine``: its scorer feeds each ``ObuMetrics``
it decodes (``feed``) into the same ``TelemetryBoard`` as ``v2i monitor``, and the line shows
elapsed / total s, output and RSU deadline misses (run, and the last 10 s), the current
mode(s), RSU lists received, chaos events played.
"""

from __future__ import annotations

import shutil
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TextIO

from schemas.messages import ObuMetrics

from v2i.telemetry.snapshot import TelemetryBoard

REFRESH_S = 0.5
PLAIN_EVERY_S = 5.0
CLEAR = "\r\x1b[K"  # carriage return, erase to the end of the line


def pct(value: float | None) -> str:
    return "-" if value is None else f"{value:.1%}"


def format_line(prog: str, totals: dict[str, Any], elapsed_s: float, total_s: float,
                events: tuple[int, int] = (0, 0), window_s: float = 10.0) -> str:
    """One line from ``TelemetryBoard.totals()``; ``events``: chaos events (played, in the timeline)."""
    if elapsed_s < 0:
        return f"{prog}: the services are ready, the run begins in {-elapsed_s:.1f} s"
    parts = [f"{prog} {min(elapsed_s, total_s):5.1f}/{total_s:g} s"]
    if totals["vehicles"] == 0:
        parts.append("waiting for the OBU's metrics")
    else:
        out, rsu = totals["output_miss_ratio"], totals["rsu_miss_ratio"]
        modes = totals["modes"]
        mode = next(iter(modes)) if len(modes) == 1 else ", ".join(f"{m} {n}" for m, n in sorted(modes.items()))
        parts.append(f"mode {mode}")
        parts.append(f"misses: output {totals['output_deadline_misses']}/{totals['cycles']} {pct(out['run'])} "
                     f"({window_s:g} s {pct(out['window'])}), RSU {pct(rsu['run'])} ({window_s:g} s {pct(rsu['window'])})")
        parts.append(f"RSU lists {totals['rsu_lists_received']}")
        if totals["vehicles"] > 1:
            parts.append(f"{totals['vehicles']} vehicles")
    if events[1]:
        parts.append(f"chaos {events[0]}/{events[1]}")
    return " | ".join(parts)


class _LineAwareStderr:
    """Stands in for ``sys.stderr`` while the line shows. Text is held per thread until its line is
    complete (``print`` writes the text, then "\\n"); each complete line is written whole: the status
    line erased, the text, the status line drawn again."""

    def __init__(self, status: StatusLine, real: TextIO):
        self._status, self._real = status, real
        self._partial: dict[int, str] = {}  # thread id -> text written without its newline yet

    def write(self, text: str) -> int:
        status, me = self._status, threading.get_ident()
        with status.lock:
            held = self._partial.pop(me, "") + text
            whole, newline, rest = held.rpartition("\n")
            if rest:
                self._partial[me] = rest
            if newline:
                self._real.write(CLEAR + whole + newline + status.shown)
                self._real.flush()
        return len(text)

    def close_lines(self) -> None:
        """Write what is still held (text never ended by a newline), each on its own line."""
        with self._status.lock:
            for text in self._partial.values():
                self._real.write(CLEAR + text + "\n")
            self._partial.clear()

    def flush(self) -> None:
        self._real.flush()

    def __getattr__(self, name: str):
        return getattr(self._real, name)


class StatusLine:
    """One status line on stderr from ``text()`` and its drawing thread; ``start`` / ``stop`` around
    what it describes."""

    def __init__(self, text: Callable[[], str], stream: TextIO | None = None, tty: bool | None = None):
        self.text = text
        self.stream = sys.stderr if stream is None else stream
        self.tty = self.stream.isatty() if tty is None else tty
        self.lock = threading.Lock()
        self.shown = ""  # the line as last drawn (tty)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_plain_s = float("-inf")
        self._saved_stderr: TextIO | None = None

    def line(self) -> str:
        return self.text()

    def draw(self) -> None:
        """Redraw in place (tty), or print a plain line when ``PLAIN_EVERY_S`` has passed."""
        text = self.line()
        if self.tty:
            width = shutil.get_terminal_size((100, 24)).columns
            with self.lock:
                self.shown = text[:max(width - 1, 20)]
                self.stream.write(CLEAR + self.shown)
                self.stream.flush()
        elif time.monotonic() - self._last_plain_s >= PLAIN_EVERY_S:
            self._last_plain_s = time.monotonic()
            print(text, file=self.stream, flush=True)

    def _loop(self) -> None:
        while not self._stop.wait(REFRESH_S):
            self.draw()

    def start(self) -> None:
        if self.tty and self.stream is sys.stderr:
            self._saved_stderr, sys.stderr = sys.stderr, _LineAwareStderr(self, sys.stderr)
        self._stop.clear()
        self.draw()
        self._thread = threading.Thread(target=self._loop, name="live-line", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """End the thread; on a terminal, erase the line (the summary follows)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self._saved_stderr is not None:
            if isinstance(sys.stderr, _LineAwareStderr):
                sys.stderr.close_lines()
            sys.stderr, self._saved_stderr = self._saved_stderr, None
        if self.tty:
            with self.lock:
                self.stream.write(CLEAR)
                self.stream.flush()
                self.shown = ""


class LiveLine(StatusLine):
    """The run's line: progress, misses, mode, RSU lists, chaos events (``format_line``)."""

    def __init__(self, prog: str, start_ns: int, duration_s: float, events: Callable[[], tuple[int, int]] = lambda: (0, 0),
                 stream: TextIO | None = None, tty: bool | None = None):
        super().__init__(self._text, stream, tty)
        self.prog, self.start_ns, self.duration_s, self.events = prog, start_ns, duration_s, events
        self.board = TelemetryBoard()

    def feed(self, metrics: ObuMetrics) -> None:
        """One OBU metrics message, as the scorer decoded it (any thread)."""
        with self.lock:
            self.board.on_obu_metrics(metrics, time.monotonic_ns())

    def _text(self) -> str:
        with self.lock:
            totals = self.board.totals()
        elapsed_s = (time.time_ns() - self.start_ns) * 1e-9
        return format_line(self.prog, totals, elapsed_s, self.duration_s, self.events(), self.board.window_s)
