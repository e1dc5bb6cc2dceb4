"""Indexed columns of an objects section: a column sent as positions in a table of its values.

A column with few distinct values spread over a wide range (variances of standard deviations on a
0.01 m grid, confidences, sizes of a few vehicle types) costs ``ceil(log2 U)`` bits per object
instead of ``w`` when each object sends the position of its value among the column's ``U``
distinct values ``0 = T_0 < T_1 < ... < T_(U-1)`` (values after ``ref`` and ``scale``,
``schemas.object_wire``), plus the table once per message.

Wire: the section's ``tables`` entry is ``[counts, sizes, blob]``: ``counts`` the ``U_j`` of each
indexed column in layout order, ``sizes`` one byte per table, its item size ``b_j`` (1, 2, 4 or 8:
the fewest bytes its largest gap needs), ``blob`` the tables back to back, each as ``U_j``
little-endian unsigned ``b_j``-byte gaps ``T_k - T_(k-1)`` with a 0 in place of ``T_0``. So one
cumulative sum over all the gaps, ``C``, holds every table: ``T_k = C[s + k] - C[s]`` for a table
starting at ``s``. No tables: ``[]``.

The encoder indexes column j iff it is smaller: ``N (w_j - ceil(log2 U_j)) > 8 U_j b_j``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from schemas import bitpack
from schemas.errors import MalformedMessage

NO_TABLES: tuple = ()
_ITEMSIZES = np.array([1, 2, 4, 8])
_ITEM_LIMITS = np.array([2**8 - 1, 2**16 - 1, 2**32 - 1])  # the largest gap of each item size
_MAX_VALUE = 1 << bitpack.MAX_WIDTH


def index_columns(fields: np.ndarray, widths: np.ndarray) -> tuple[list[Any], np.ndarray]:
    """Replace, in place, the (N, F) non-negative ``fields`` of each column that is smaller indexed
    by its positions in its distinct values, narrowing ``widths`` (F,); the ``tables`` entry and
    the (F,) indexed mask."""
    n = len(fields)
    ordered = np.sort(fields, axis=0)
    gaps = np.zeros_like(ordered)  # (N, F): row 0 and between equal values 0
    np.subtract(ordered[1:], ordered[:-1], out=gaps[1:])
    steps = gaps > 0
    distinct = 1 + np.count_nonzero(steps, axis=0)
    index_bits = bitpack.bit_lengths(distinct - 1)
    itemsize = _ITEMSIZES[np.searchsorted(_ITEM_LIMITS, gaps.max(axis=0))]
    indexed = n * (widths - index_bits) > 8 * distinct * itemsize
    cols = np.flatnonzero(indexed)
    if not len(cols):
        return list(NO_TABLES), indexed
    sub = fields[:, cols]
    order = np.argsort(sub, axis=0, kind="stable")
    sub[order, np.arange(len(cols))] = np.cumsum(steps[:, cols], axis=0)  # rank among the distinct values
    fields[:, cols] = sub
    widths[cols] = index_bits[cols]
    keep = steps[:, cols]
    keep[0] = True
    table_gaps = gaps[:, cols].T[keep.T]  # each table's 0 and non-zero gaps, table after table
    sizes, counts = itemsize[cols], distinct[cols]
    return [counts.tolist(), sizes.astype(np.uint8).tobytes(), _narrow(table_gaps, np.repeat(sizes, counts))], indexed


class ValueTables:
    """The decoded ``tables`` entry of a section with ``n`` objects and the (F,) ``indexed`` mask."""

    def __init__(self, entry: Any, indexed: np.ndarray, n: int):
        counts, sizes, blob = _entry(entry)
        k = int(indexed.sum())
        if len(counts) != k or len(sizes) != k:
            raise MalformedMessage(f"objects: {k} indexed columns but {len(counts)} tables, {len(sizes)} sizes")
        if not all(type(c) is int and 1 <= c <= max(n, 1) for c in counts):
            raise MalformedMessage(f"objects: a table must hold 1..{max(n, 1)} values")
        if not set(sizes) <= {1, 2, 4, 8}:
            raise MalformedMessage("objects: a table's item size must be 1, 2, 4 or 8 bytes")
        item = np.frombuffer(sizes, dtype=np.uint8)
        self.counts = np.array(counts, dtype=np.int64)
        self.starts = np.cumsum(self.counts) - self.counts
        if int(self.counts @ item) != len(blob):
            raise MalformedMessage(f"objects: tables of {int(self.counts @ item)} bytes, {len(blob)} sent")
        gaps = _widen(blob, np.repeat(item, self.counts))
        if (gaps > _MAX_VALUE).any():
            raise MalformedMessage(f"objects: a table gap above 2^{bitpack.MAX_WIDTH}")
        if not np.array_equal(np.flatnonzero(gaps == 0), self.starts):
            raise MalformedMessage("objects: a table must start with 0 and then strictly increase")
        self._c = np.cumsum(gaps.astype(np.int64))  # <= 27 x 1024 gaps of <= 2^48: below 2^63
        self.top = self._c[self.starts + self.counts - 1] - self._c[self.starts]
        if (self.top >= _MAX_VALUE).any():
            raise MalformedMessage(f"objects: a table value above 2^{bitpack.MAX_WIDTH}")

    @property
    def sums(self) -> np.ndarray:
        """(M,) int64 cumulative sum of every table's gaps: ``T_k = sums[s + k] - sums[s]``."""
        return self._c

    def lookup(self, positions: np.ndarray) -> np.ndarray:
        """(N, K) values of the K indexed columns' (N, K) ``positions``."""
        if (positions >= self.counts).any():
            raise MalformedMessage("objects: a position beyond its indexed column's table")
        return self._c[self.starts + positions] - self._c[self.starts]


_BYTE = np.arange(8)


def _narrow(values: np.ndarray, sizes: np.ndarray) -> bytes:
    """(M,) non-negative ints as little-endian unsigned integers of (M,) ``sizes`` bytes each."""
    return values.astype("<u8").view(np.uint8).reshape(-1, 8)[_BYTE < sizes[:, None]].tobytes()


def _widen(blob: bytes, sizes: np.ndarray) -> np.ndarray:
    """(M,) uint64 of ``_narrow``'s bytes (``len(blob) == sizes.sum()``)."""
    out = np.zeros((len(sizes), 8), dtype=np.uint8)
    out[_BYTE < sizes[:, None]] = np.frombuffer(blob, dtype=np.uint8)
    return out.view("<u8").ravel()


def _entry(entry: Any) -> tuple[list, bytes, bytes]:
    if entry == []:
        return [], b"", b""
    if not (isinstance(entry, list) and len(entry) == 3 and isinstance(entry[0], list)
            and isinstance(entry[1], bytes) and isinstance(entry[2], bytes)):
        raise MalformedMessage("objects: tables must be [counts, sizes, blob]: an array and two byte strings")
    return entry[0], entry[1], entry[2]
