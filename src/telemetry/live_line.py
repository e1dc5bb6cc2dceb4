"""The compact live line of ``v2i demo`` / ``v2i chaos run``: progress, misses, mode, on stderr.

The demo's scorer feeds each ``ObuMetrics`` it decodes (``feed``); a thread redraws one line
every ``REFRESH_S`` from the same ``TelemetryBoard`` as ``v2i monitor``: elapsed / total s,
output and RSU deadline misses (run, and the last 10 s), the current mode(s), RSU lists
received, chaos events played. On a terminal the line is rewritten in place (``\\r``, cut to
the terminal's width) and this process's own stderr lines (the demo's log) are printed above
it; elsewhere (a file, a pipe, CI) a plain line every ``PLAIN_EVERY_S``. stdout is never
touched, so ``--json -`` stays clean.
"""

from __future__ import annotations

import shutil
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TextIO

from schemas.messages import ObuMetrics

from .snapshot import TelemetryBoard

REFRESH_S = 0.5
PLAIN_EVERY_S = 5.0
CLEAR = "\r\x1b[K"  # carriage return, erase to the end of the line


def pct(value: float | None) -> str:
    return "-" if value is None else f"{value:.1%}"


def format_line(prog: str, totals: dict[str, Any], elapsed_s: float, total_s: float,
                events: tuple[int, int] = (0, 0), window_s: float = 10.0) -> str:
    """One line from ``TelemetryBoard.totals()``; ``events``: chaos events (played, in the timeline)."""
    if elapsed_s < 0:
        return f"{prog}: starting the services, the run begins in {-elapsed_s:.1f} s"
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
    """Stands in for ``sys.stderr`` while the line shows: a write first erases the line, and the
    line is drawn again after a complete line of text."""

    def __init__(self, live: LiveLine, real: TextIO):
        self._live, self._real = live, real

    def write(self, text: str) -> int:
        live = self._live
        with live.lock:
            if not live.mid_line:  # print() writes the text, then "\n": erase before the first part only
                self._real.write(CLEAR)
            n = self._real.write(text)
            live.mid_line = not text.endswith("\n")
            if not live.mid_line:
                self._real.write(live.shown)
            self._real.flush()
        return n

    def flush(self) -> None:
        self._real.flush()

    def __getattr__(self, name: str):
        return getattr(self._real, name)


class LiveLine:
    """The line's state and its drawing thread; ``start`` / ``stop`` around the run."""

    def __init__(self, prog: str, start_ns: int, duration_s: float, events: Callable[[], tuple[int, int]] = lambda: (0, 0),
                 stream: TextIO | None = None, tty: bool | None = None):
        self.prog, self.start_ns, self.duration_s, self.events = prog, start_ns, duration_s, events
        self.stream = sys.stderr if stream is None else stream
        self.tty = self.stream.isatty() if tty is None else tty
        self.board = TelemetryBoard()
        self.lock = threading.Lock()
        self.shown = ""  # the line as last drawn (tty)
        self.mid_line = False  # another stderr line is half written (tty): do not draw over it
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_plain_s = float("-inf")
        self._saved_stderr: TextIO | None = None

    def feed(self, metrics: ObuMetrics) -> None:
        """One OBU metrics message, as the scorer decoded it (any thread)."""
        with self.lock:
            self.board.on_obu_metrics(metrics, time.monotonic_ns())

    def line(self) -> str:
        with self.lock:
            totals = self.board.totals()
        elapsed_s = (time.time_ns() - self.start_ns) * 1e-9
        return format_line(self.prog, totals, elapsed_s, self.duration_s, self.events(), self.board.window_s)

    def draw(self) -> None:
        """Redraw in place (tty), or print a plain line when ``PLAIN_EVERY_S`` has passed."""
        text = self.line()
        if self.tty:
            width = shutil.get_terminal_size((100, 24)).columns
            with self.lock:
                self.shown = text[:max(width - 1, 20)]
                if not self.mid_line:
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
        self.draw()
        self._thread = threading.Thread(target=self._loop, name="live-line", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """End the thread; on a terminal, erase the line (the summary follows)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self._saved_stderr is not None:
            sys.stderr, self._saved_stderr = self._saved_stderr, None
        if self.tty:
            with self.lock:
                self.stream.write(CLEAR)
                self.stream.flush()
                self.shown = ""
