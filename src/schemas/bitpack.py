"""Rows of unsigned integers bit-packed at per-column widths.

N rows of K unsigned fields, field j ``widths[j]`` bits wide (0..MAX_WIDTH). A row is the
integer ``sum_j d[i, j] << s_j`` with ``s_j = widths[0] + ... + widths[j-1]`` (field 0 in the
lowest bits), written little-endian in ``ceil(R / 8)`` bytes, ``R = sum(widths)``; rows follow
each other. Equal, by test, to Python's ``int.to_bytes`` of that sum.

The loops that pack and unpack rows are compiled (``schemas.bit_rows``).
"""

from __future__ import annotations

import numpy as np

MAX_WIDTH = 48  # bits of one field: a code range up to 2^48 (the widest wire column needs 32)
_POW2 = np.uint64(1) << np.arange(64, dtype=np.uint64)


def bit_lengths(values: np.ndarray) -> np.ndarray:
    """(K,) bits needed by each non-negative int64 value (0 for 0): Python's ``int.bit_length``."""
    return np.searchsorted(_POW2, values.astype(np.uint64), side="right")


def pack(fields: np.ndarray, widths: np.ndarray) -> bytes:
    """Bytes of (N, K) non-negative int64 ``fields``, each below ``2**widths[j]``."""
    from .bit_rows import pack_rows  # (numba, on first use: module docstring of bit_rows)

    return pack_rows(fields, widths, row_bytes(widths)).tobytes()


def unpack(data: bytes, n: int, widths: np.ndarray) -> np.ndarray:
    """(N, K) int64 fields of ``n`` packed rows (``len(data)`` must be ``n * row_bytes``: ValueError)."""
    from .bit_rows import unpack_rows

    return unpack_rows(np.frombuffer(data, dtype=np.uint8), n, widths, row_bytes(widths))


def row_bytes(widths: np.ndarray) -> int:
    """Bytes of one packed row: ceil(sum(widths) / 8)."""
    return -(-int(np.sum(widths)) // 8)
