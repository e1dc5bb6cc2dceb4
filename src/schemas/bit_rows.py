"""The loops of ``schemas.bitpack``, compiled (numba: ``fusion.jit``).

Imported by ``fusion.jit.load_kernels`` only; from then on ``bitpack.pack`` / ``unpack`` use them
(see bitpack). Bit b of a row's integer is bit b % 8 of the row's byte b // 8 (little-endian);
field j holds bits [s_j, s_j + w_j).
"""

from __future__ import annotations

import numpy as np

from fusion.jit import I64, IN_I1, IN_I2, IN_U1, kernel

from . import bitpack


@kernel(IN_I2, IN_I1, I64)
def pack_rows(fields: np.ndarray, widths: np.ndarray, row_bytes: int) -> np.ndarray:
    """(N * row_bytes,) uint8 of (N, K) non-negative int64 ``fields``, each below 2^widths[j]."""
    n, k = fields.shape
    out = np.zeros(n * row_bytes, np.uint8)
    for i in range(n):
        bit = 8 * row_bytes * i
        for j in range(k):
            value, left = fields[i, j], widths[j]
            while left > 0:  # the next byte's share of the field's low bits
                take = min(8 - (bit & 7), left)
                out[bit >> 3] |= (value & ((1 << take) - 1)) << (bit & 7)
                value, left, bit = value >> take, left - take, bit + take
    return out


@kernel(IN_U1, I64, IN_I1, I64)
def unpack_rows(data: np.ndarray, n: int, widths: np.ndarray, row_bytes: int) -> np.ndarray:
    """(N, K) int64 fields of ``n`` rows of ``row_bytes`` in ``data`` (uint8, exactly n * row_bytes:
    checked here too, since the bytes come from the wire)."""
    if len(data) != n * row_bytes:
        raise ValueError("packed rows: wrong length")
    out = np.zeros((n, len(widths)), np.int64)
    for i in range(n):
        bit = 8 * row_bytes * i
        for j in range(len(widths)):
            value, got = 0, 0
            while got < widths[j]:
                take = min(8 - (bit & 7), widths[j] - got)
                value |= ((np.int64(data[bit >> 3]) >> (bit & 7)) & ((1 << take) - 1)) << got
                got, bit = got + take, bit + take
            out[i, j] = value
    return out


bitpack.use_compiled(pack_rows, unpack_rows)
