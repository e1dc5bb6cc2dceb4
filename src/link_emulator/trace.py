"""Measured delay traces in CICV5G format: parsing, bundled traces and loss from gaps.

Format (whitespace-separated text, one header line, one row per received message)::

    pub_time(ms) sub_time(ms) delay(ms) utmX(m) utmY(m) ... cellid(db) sinr(db) rsrp(db)

``pub_time`` and ``sub_time`` are ms since the Unix epoch on the sender's clock and
``delay = sub_time - pub_time``. Messages were sent periodically; a missing row (a gap in
``pub_time`` longer than the period) is a lost message. The period is the median send
interval ``P``; a gap of ``dt`` hides ``round(dt / P) - 1`` lost messages.

Bundled traces live in ``link_emulator/traces/`` (see the README there for licence and
citation) and are named by their path below it, e.g. ``cicv5g/urban_n78_v20_run01.txt.gz``.
"""

from __future__ import annotations

import gzip
from dataclasses import dataclass
from functools import cached_property, lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

_TRACE_DIR = "traces"
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
    def slot_delay_ms(self) -> np.ndarray:
        """The trace on its send grid, shape (n + lost,): a delay per slot, NaN for a lost one.

        After received message i come ``max(0, round(dt_i / P) - 1)`` lost slots,
        ``dt_i = pub_{i+1} - pub_i``.
        """
        lost_after = np.maximum(np.rint(np.diff(self.pub_time_ms) / self.period_ms) - 1, 0).astype(np.int64)
        slots = np.full(self.delay_ms.size + int(lost_after.sum()), np.nan)
        # index of received message i on the grid: i + number of lost slots before it
        slots[np.arange(self.delay_ms.size) + np.concatenate(([0], np.cumsum(lost_after)))] = self.delay_ms
        return slots

    @property
    def loss_ratio(self) -> float:
        """Lost slots / all slots."""
        return float(np.mean(np.isnan(self.slot_delay_ms)))

    @property
    def mean_burst_len(self) -> float:
        """Mean length (in slots) of runs of consecutive lost slots; 0 when none is lost."""
        return mean_run_length(np.isnan(self.slot_delay_ms))


def mean_run_length(flags: np.ndarray) -> float:
    """Mean length of the runs of consecutive True values in a 1-D bool array; 0.0 if none."""
    flags = np.asarray(flags, dtype=bool)
    if not flags.any():
        return 0.0
    # a run starts where flags[k] and not flags[k - 1]
    starts = np.count_nonzero(flags[1:] & ~flags[:-1]) + int(flags[0])
    return float(np.count_nonzero(flags) / starts)


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
    bundled = resources.files("link_emulator") / _TRACE_DIR / name_or_path
    if bundled.is_file():
        raw, source = bundled.read_bytes(), f"bundled {name_or_path}"
    else:
        try:
            raw, source = Path(name_or_path).read_bytes(), str(name_or_path)
        except OSError as exc:
            raise TraceError(f"cannot read trace {name_or_path!r}: not a bundled trace "
                             f"({', '.join(bundled_traces())}) nor a readable file ({exc.strerror})") from None
    try:
        text = (gzip.decompress(raw) if str(name_or_path).endswith(".gz") else raw).decode("utf-8")
    except (OSError, UnicodeDecodeError, EOFError) as exc:
        raise TraceError(f"trace {source}: cannot decode ({exc})") from None
    return parse_cicv5g(text, source)
