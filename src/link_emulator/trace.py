"""Measured delay traces in CICV5G format: parsing, bundled traces and loss from gaps.

Format (whitespace-separated text, one header line, one row per received message)::

    pub_time(ms) sub_time(ms) delay(ms) utmX(m) utmY(m) ... cellid(db) sinr(db) rsrp(db)

``pub_time`` and ``sub_time`` are ms since the Unix epoch on the sender's clock and
``delay = sub_time - pub_time``. Messages were sent about periodically; a missing row (a gap
in ``pub_time`` longer than the period) is a lost message. The period is the median send
interval ``P``; a gap of ``dt`` hides ``round(dt / P) - 1`` lost messages.

Replayed in a loop (``processes.TraceClock``), the trace keeps its own irregular send times:
row i owns the send times ``[p_i, p_{i+1})``, ``dt_i = p_{i+1} - p_i``. Each of the ``m_i``
messages lost in its gap takes one period of it, at its end; the row keeps the first
``dt_i - m_i P`` (at least ``P / 2``, since ``dt_i / P >= m_i + 1/2``). The loop closes one
interval after the last row (see ``DelayTrace.loop_ms``).

Bundled traces live in ``link_emulator/traces/`` (see the README there for licence and
citation) and are named by their path below it, e.g. ``cicv5g/urban_n78_v20_run01.txt.gz``.
"""

from __future__ import annotations

import gzip
import io
from dataclasses import dataclass
from functools import cached_property, lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

from v2i.core.files import FileMissing, FileRefused, MiB, read_bounded, size_text

_TRACE_DIR = "traces"
# A delay trace, read whole and, gzipped, decompressed whole: the bundled one is 105 kB gzipped, ~30
# bytes a row; 64 MiB holds two million rows (a gzip bomb stops there too).
TRACE_LIMIT_BYTES = 64 * MiB
REQUIRED_COLUMNS = ("pub_time(ms)", "sub_time(ms)", "delay(ms)")


class TraceError(ValueError):
    """A trace file that cannot be read or parsed; the message names the file and the line."""


@dataclass(frozen=True)
class DelayTrace:
    """One trace: send times and delays of the received messages, in ms."""

    source: str
    pub_time_ms: np.ndarray  # (n,) send times, strictly increasing
    delay_ms: np.ndarray  # (n,) one-way delays, >= 0

    @cached_property
    def period_ms(self) -> float:
        """The send period P: the median interval between consecutive send times (ms)."""
        return float(np.median(np.diff(self.pub_time_ms)))

    @cached_property
    def loop_ms(self) -> float:
        """Length L of one replay loop (ms): the trace's send span plus one period, or more.

        Row 0 of the next loop is sent at ``p_0 + L`` and arrives at ``a_0 + L`` (``a = p + delay``);
        ``L = max(p_{n-1} - p_0 + P, a_{n-1} - a_0)`` so that the loop seam never reorders.
        """
        sent_span_ms = float(self.pub_time_ms[-1] - self.pub_time_ms[0])
        arrival_span_ms = sent_span_ms + float(self.delay_ms[-1] - self.delay_ms[0])
        return max(sent_span_ms + self.period_ms, arrival_span_ms)

    @cached_property
    def interval_ms(self) -> np.ndarray:
        """dt_i = p_{i+1} - p_i (ms), shape (n,); the last one closes the loop (to ``p_0 + L``)."""
        return np.diff(self.pub_time_ms, append=self.pub_time_ms[0] + self.loop_ms)

    @cached_property
    def lost_after(self) -> np.ndarray:
        """m_i = max(0, round(dt_i / P) - 1): messages lost in the gap after row i, int, shape (n,)."""
        return np.maximum(np.rint(self.interval_ms / self.period_ms) - 1, 0).astype(np.int64)

    @cached_property
    def own_slot_ms(self) -> np.ndarray:
        """Length of row i's own send slot, dt_i - m_i P (ms, >= P / 2), shape (n,); the rest of dt_i is lost."""
        return self.interval_ms - self.lost_after * self.period_ms

    @property
    def loss_ratio(self) -> float:
        """Lost share of the loop's send time, sum(m_i) P / L: the loss of a sender not in step with the trace.

        Close to the lost share of send slots, sum(m) / (n + sum(m)), when the mean slot is about P.
        """
        return float(self.lost_after.sum() * self.period_ms / self.loop_ms)

    @property
    def mean_burst_len(self) -> float:
        """Mean gap (run of lost slots) length in slots, sum(m_i) / #{m_i > 0}; 0 when none is lost."""
        gaps = self.lost_after[self.lost_after > 0]
        return float(gaps.mean()) if gaps.size else 0.0

    @property
    def overtaken_ratio(self) -> float:
        """Share of the trace's rows received after a later-sent row (0 for a trace that never reorders)."""
        return overtaken_ratio(self.pub_time_ms + self.delay_ms)


def mean_run_length(flags: np.ndarray) -> float:
    """Mean length of the runs of consecutive True values in a 1-D bool array; 0.0 if none."""
    flags = np.asarray(flags, dtype=bool)
    if not flags.any():
        return 0.0
    # a run starts where flags[k] and not flags[k - 1]
    starts = np.count_nonzero(flags[1:] & ~flags[:-1]) + int(flags[0])
    return float(np.count_nonzero(flags) / starts)


def overtaken_ratio(arrival: np.ndarray) -> float:
    """Share of messages, given in send order with arrival times (shape (n,)), that a later-sent one overtook.

    Message k is overtaken when min_{j > k} arrival_j < arrival_k (ties are not overtaking).
    """
    arrival = np.asarray(arrival)
    if arrival.size < 2:
        return 0.0
    later_min = np.minimum.accumulate(arrival[::-1])[::-1][1:]  # min over j > k, for k < n - 1
    return float(np.count_nonzero(later_min < arrival[:-1]) / arrival.size)


def parse_cicv5g(text: str, source: str) -> DelayTrace:
    """The trace in ``text`` (CICV5G format); TraceError naming ``source`` and the line otherwise."""
    lines = text.splitlines()
    if not lines or not lines[0].strip():
        raise TraceError(f"trace {source}: empty file, expected a header line with {' '.join(REQUIRED_COLUMNS)}")
    header = lines[0].split()
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise TraceError(f"trace {source} line 1: header lacks column(s) {', '.join(missing)}")
    cols = [header.index(c) for c in REQUIRED_COLUMNS]
    rows = [_parse_row(line, number, cols, source) for number, line in enumerate(lines[1:], 2) if line.strip()]
    if len(rows) < 2:
        raise TraceError(f"trace {source}: needs at least 2 data rows, got {len(rows)}")
    data = np.array(rows)
    _check_increasing(data[:, 0], source)
    return DelayTrace(source, data[:, 0], data[:, 2])


def _parse_row(line: str, number: int, cols: list[int], source: str) -> tuple[float, float, float]:
    """(pub_ms, sub_ms, delay_ms) of one data line, checked."""
    fields = line.split()
    if len(fields) <= max(cols):
        raise TraceError(f"trace {source} line {number}: expected at least {max(cols) + 1} columns, got {len(fields)}")
    try:
        pub_ms, sub_ms, delay_ms = (float(fields[c]) for c in cols)
    except ValueError:
        raise TraceError(f"trace {source} line {number}: pub_time, sub_time and delay must be numbers") from None
    if not all(np.isfinite((pub_ms, sub_ms, delay_ms))):
        raise TraceError(f"trace {source} line {number}: non-finite time or delay")
    if delay_ms < 0:
        raise TraceError(f"trace {source} line {number}: negative delay {delay_ms:g} ms")
    if abs(sub_ms - pub_ms - delay_ms) > 1.0:  # the files store whole ms
        raise TraceError(f"trace {source} line {number}: delay {delay_ms:g} != sub_time - pub_time = {sub_ms - pub_ms:g}")
    return pub_ms, sub_ms, delay_ms


def _check_increasing(pub_ms: np.ndarray, source: str) -> None:
    bad = np.flatnonzero(np.diff(pub_ms) <= 0)
    if bad.size:
        raise TraceError(f"trace {source} line {int(bad[0]) + 3}: pub_time not after the previous row's")


def bundled_traces() -> list[str]:
    """Names (paths below ``link_emulator/traces``) of the shipped trace files, sorted."""
    root = resources.files("link_emulator") / _TRACE_DIR
    return sorted(
        f"{folder.name}/{f.name}"
        for folder in root.iterdir()
        if folder.is_dir()
        for f in folder.iterdir()
        if f.name.endswith((".txt", ".txt.gz"))
    )


@lru_cache(maxsize=16)
def load_trace(name_or_path: str) -> DelayTrace:
    """A bundled trace by name or a trace file by path (``.gz`` is decompressed); cached."""
    bundled = Path(str(resources.files("link_emulator") / _TRACE_DIR)) / name_or_path
    path, source = (bundled, f"bundled {name_or_path}") if bundled.is_file() else (Path(name_or_path), str(name_or_path))
    try:
        raw = read_bounded(path, TRACE_LIMIT_BYTES, "trace")
    except FileMissing:
        raise TraceError(f"cannot read trace {name_or_path!r}: not a bundled trace "
                         f"({', '.join(bundled_traces())}) nor an existing file") from None
    except FileRefused as exc:
        raise TraceError(str(exc)) from None
    try:
        text = (_gunzip(raw, source) if str(name_or_path).endswith(".gz") else raw).decode("utf-8")
    except (OSError, UnicodeDecodeError, EOFError) as exc:
        raise TraceError(f"trace {source}: cannot decode ({exc})") from None
    return parse_cicv5g(text, source)


def _gunzip(raw: bytes, source: str) -> bytes:
    """``raw`` decompressed, at most ``TRACE_LIMIT_BYTES``; TraceError beyond."""
    with gzip.GzipFile(fileobj=io.BytesIO(raw)) as f:
        data = f.read(TRACE_LIMIT_BYTES + 1)
    if len(data) > TRACE_LIMIT_BYTES:
        raise TraceError(f"trace {source}: over {size_text(TRACE_LIMIT_BYTES)} decompressed; a trace must be "
                         f"at most {size_text(TRACE_LIMIT_BYTES)}")
    return data
