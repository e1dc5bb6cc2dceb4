"""Rows of unsigned integers bit-packed at per-column widths.

N rows of K unsigned fields, field j ``widths[j]`` bits wide (0..MAX_WIDTH). A row is the
integer ``sum_j d[i, j] << s_j`` with ``s_j = widths[0] + ... + widths[j-1]`` (field 0 in the
lowest bits), written little-endian in ``ceil(R / 8)`` bytes, ``R = sum(widths)``; rows follow
each other. Equal, by test, to Python's ``int.to_bytes`` of that sum.

In numpy: a row is a few 64-bit lanes, field j in lane ``s_j // 64`` at shift ``s_j % 64``, its
high bits spilling into the next lane when ``s_j % 64 + w_j > 64``
(tests/unit/test_wire_differential.py). A process that has loaded its kernels packs a whole
objects section in one compiled loop instead (``schemas.bit_rows.pack_section``: the same bytes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_WIDTH = 48  # bits of one field: a code range up to 2^48 (the widest wire column needs 32)
_POW2 = np.uint64(1) << np.arange(64, dtype=np.uint64)


def bit_lengths(values: np.ndarray) -> np.ndarray:
    """(K,) bits needed by each non-negative int64 value (0 for 0): Python's ``int.bit_length``."""
    return np.searchsorted(_POW2, values.astype(np.uint64), side="right")


@dataclass(frozen=True)
class RowLayout:
    """Where each non-empty field sits in a row. ``cols`` (F,) field indices with width > 0,
    ``lane``/``shift``/``mask`` (F,) uint64-ready, ``spill`` (S,) positions in ``cols`` of the
    fields crossing a lane boundary, ``lanes`` 64-bit lanes per row, ``row_bytes`` bytes per row."""

    cols: np.ndarray
    lane: np.ndarray
    shift: np.ndarray
    mask: np.ndarray
    spill: np.ndarray
    lanes: int
    row_bytes: int

    @classmethod
    def of(cls, widths: np.ndarray) -> RowLayout:
        widths = np.asarray(widths, dtype=np.int64)
        starts = np.concatenate([[0], np.cumsum(widths)[:-1]]) if len(widths) else widths
        total = int(widths.sum())
        cols = np.flatnonzero(widths)
        s, w = starts[cols], widths[cols]
        mask = np.where(w >= 64, np.uint64(2**64 - 1), (np.uint64(1) << w.astype(np.uint64)) - np.uint64(1))
        return cls(cols, s >> 6, (s & 63).astype(np.uint64), mask.astype(np.uint64),
                   np.flatnonzero((s & 63) + w > 64), -(-total // 64), -(-total // 8))


def pack(fields: np.ndarray, widths: np.ndarray) -> bytes:
    """Bytes of (N, K) non-negative int64 ``fields``, each below ``2**widths[j]``."""
    layout = RowLayout.of(widths)
    n = len(fields)
    if layout.row_bytes == 0 or n == 0:
        return b""
    d = fields[:, layout.cols].astype(np.uint64)
    low = d << layout.shift  # bits past 64 fall off here and come back as the spill
    lanes = np.zeros((n, layout.lanes), dtype=np.uint64)
    firsts, starts = np.unique(layout.lane, return_index=True)
    lanes[:, firsts] = np.bitwise_or.reduceat(low, starts, axis=1)  # disjoint bits: OR = sum
    if len(layout.spill):
        k = layout.spill
        lanes[:, layout.lane[k] + 1] |= d[:, k] >> (np.uint64(64) - layout.shift[k])
    rows = lanes.astype("<u8", copy=False).view(np.uint8)
    return rows[:, :layout.row_bytes].tobytes()


def unpack(data: bytes, n: int, widths: np.ndarray) -> np.ndarray:
    """(N, K) int64 fields of ``n`` packed rows (``len(data)`` must be ``n * row_bytes``: ValueError)."""
    layout = RowLayout.of(widths)
    if len(data) != n * layout.row_bytes:
        raise ValueError(f"packed rows: {len(data)} bytes, {n} rows of {layout.row_bytes} expected")
    out = np.zeros((n, len(widths)), dtype=np.int64)
    if layout.row_bytes == 0 or n == 0:
        return out
    raw = np.zeros((n, 8 * layout.lanes), dtype=np.uint8)
    raw[:, :layout.row_bytes] = np.frombuffer(data, dtype=np.uint8).reshape(n, layout.row_bytes)
    lanes = raw.view("<u8")
    d = lanes[:, layout.lane] >> layout.shift
    if len(layout.spill):
        k = layout.spill
        d[:, k] |= lanes[:, layout.lane[k] + 1] << (np.uint64(64) - layout.shift[k])
    out[:, layout.cols] = (d & layout.mask).view(np.int64)
    return out


def row_bytes(widths: np.ndarray) -> int:
    """Bytes of one packed row: ceil(sum(widths) / 8)."""
    return -(-int(np.sum(widths)) // 8)
