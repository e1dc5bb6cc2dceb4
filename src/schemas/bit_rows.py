"""The codec's loops, compiled (numba: ``v2i.core.jit``): an objects section packed (``pack_section``)
and a float table checked and quantised (``quantize_values``), each in one pass instead of ~15-60
numpy calls on a few rows.

Imported by ``v2i.core.jit.load_kernels`` only; from then on ``object_wire.pack_objects`` and
``ObjectColumns.from_values`` use them (their numpy paths stay for processes without kernels and
are their references: tests/unit/test_object_wire_paths.py and test_columns_paths.py hold both to
the same results). On the calls recorded in a whole ``v2i eval`` (alternating, median of 9, a busy
2-core machine) ``pack_section`` takes 13 us per list against numpy's 93 (2.3 % of a
connected-intersection run, 2.1 % of red-light-runner) and ``quantize_values`` 3.4 against 26 us
(0.7 %, 1.0 %). The section's unpacking (0.15-0.4 % of a run) and the gridding of predicted paths
(0.4-0.8 %) saved less than ~1 % and are numpy only. Bit b of a row's integer is bit b % 8 of the
row's byte b // 8 (little-endian); field j holds bits [s_j, s_j + w_j).
"""

from __future__ import annotations

import numpy as np

from v2i.core.jit import I64, IN_F2, IN_I2, helper, kernel

from schemas import columns, object_wire
from schemas.columns import _YAW_HALF_TURN as YAW_HALF_TURN  # yaw codes live in [-1800, 1800)
from schemas.quantize import YAW_RAD

_SCALED, _INDEXED = object_wire._SCALED, object_wire._INDEXED  # a column's flag bits in its width byte


@helper
def _packed(fields: np.ndarray, widths: np.ndarray, row_bytes: int) -> np.ndarray:
    """(N * row_bytes,) uint8 of (N, K) non-negative int64 ``fields``, each below 2^widths[j]: ``schemas.bitpack.pack``
    as ``pack_section`` packs its rows."""
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


@helper
def _gcd(a: int, b: int) -> int:
    """gcd of two non-negative ints (Euclid; np.gcd's value)."""
    while b:
        a, b = b, a % b
    return a


@helper
def _bit_length(v: int) -> int:
    """Bits of a non-negative int (0 for 0): Python's ``int.bit_length``."""
    bits = 0
    while v:
        v >>= 1
        bits += 1
    return bits


@helper
def _position(values: np.ndarray, u: int, v: int) -> int:
    """Index of v in the ascending ``values[:u]`` that hold it (binary search)."""
    lo, hi = 0, u - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if values[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@kernel(IN_I2, IN_I2, IN_I2)
def pack_section(codes: np.ndarray, sorted_codes: np.ndarray, code_table: np.ndarray) -> tuple:
    """``object_wire.pack_objects``' section entries of (N, K) valid ``codes`` (N >= 1; ``sorted_codes``:
    each column sorted, ``np.sort(codes, axis=0)``: numpy's sort beats a compiled one past a few tens
    of rows, and numba's sort compiles in ~4 s): the present mask (required columns, and those with
    some code not the default; F of them), per present column its flag byte (width w, | 0x40 scaled, |
    0x80 indexed) and ref (the smallest code), the scales above 1 (gcd of the codes' distances to ref),
    the packed rows (N * row_bytes,) uint8, and per indexed column its table's size U and item size b,
    then the tables' gaps, narrowed (``value_tables``). A column's fields are ``(code - ref) / scale``,
    width the bits of the largest; it is indexed (fields: their positions among the U distinct fields,
    width: bits(U - 1)) iff n (w - bits(U - 1)) > 8 U b, b the item size of the largest gap between
    neighbouring distinct fields (``value_tables.index_columns``' rule)."""
    n, k = codes.shape
    present = np.zeros(k, np.bool_)
    for j in range(k):
        present[j] = code_table[3, j] != 0
        for i in range(n):
            present[j] |= codes[i, j] != code_table[0, j]
    f = int(present.sum())
    cols, ref, scale, width = np.zeros(f, np.int64), np.zeros(f, np.int64), np.zeros(f, np.int64), np.zeros(f, np.int64)
    distinct, itemsize = np.zeros(f, np.int64), np.zeros(f, np.int64)
    fields = np.zeros((n, f), np.int64)
    ordered, values = np.zeros(n, np.int64), np.zeros(n, np.int64)  # a column's sorted fields, its distinct ones
    blob, used = np.zeros(8 * n * f, np.uint8), 0
    c = 0
    for j in range(k):
        if not present[j]:
            continue
        low, g, top = codes[0, j], 0, 0
        for i in range(n):
            low = min(low, codes[i, j])
        for i in range(n):
            g = _gcd(g, codes[i, j] - low)
        g = max(g, 1)
        for i in range(n):
            fields[i, c] = (codes[i, j] - low) // g
            top = max(top, fields[i, c])
        for i in range(n):  # (code - low) // g keeps the order: g divides every code - low
            ordered[i] = (sorted_codes[i, j] - low) // g
        u, gap, values[0] = 1, 0, ordered[0]
        for i in range(1, n):
            if ordered[i] > ordered[i - 1]:
                values[u], u, gap = ordered[i], u + 1, max(gap, ordered[i] - ordered[i - 1])
        b = 1 if gap <= 0xFF else 2 if gap <= 0xFFFF else 4 if gap <= 0xFFFFFFFF else 8
        cols[c], ref[c], scale[c], width[c] = j, low, g, _bit_length(top)
        if n * (width[c] - _bit_length(u - 1)) > 8 * u * b:
            distinct[c], itemsize[c], width[c] = u, b, _bit_length(u - 1)
            for i in range(n):  # the field's position among the distinct fields
                fields[i, c] = _position(values, u, fields[i, c])
            for v in range(u):  # gaps T_v - T_(v-1), 0 first, little-endian in b bytes
                step = values[v] - values[v - 1] if v else 0
                for byte in range(b):
                    blob[used + byte] = (step >> (8 * byte)) & 0xFF
                used += b
        c += 1
    mask, flags, n_scaled, n_indexed = 0, np.zeros(f, np.uint8), 0, 0
    for c in range(f):  # the section's entries (object_wire's layout): mask, flag bytes, kept scales and tables
        mask |= 1 << cols[c]
        flags[c] = width[c] | (_SCALED if scale[c] > 1 else 0) | (_INDEXED if distinct[c] else 0)
        n_scaled += scale[c] > 1
        n_indexed += distinct[c] > 0
    scales, counts, sizes = np.zeros(n_scaled, np.int64), np.zeros(n_indexed, np.int64), np.zeros(n_indexed, np.uint8)
    n_scaled, n_indexed = 0, 0
    for c in range(f):
        if scale[c] > 1:
            scales[n_scaled], n_scaled = scale[c], n_scaled + 1
        if distinct[c]:
            counts[n_indexed], sizes[n_indexed], n_indexed = distinct[c], itemsize[c], n_indexed + 1
    return mask, flags, ref, scales, _packed(fields, width, (width.sum() + 7) // 8), counts, sizes, blob[:used]


@kernel(IN_F2, IN_F2, I64)
def quantize_values(table: np.ndarray, value_table: np.ndarray, yaw_col: int) -> tuple:
    """(N, K) codes of an (N, K) float table (``columns.ObjectColumns.from_values``) and the first value
    it refuses as a flat index ``i * K + j`` (-1: none; then the codes are not meaningful). A value
    passes when finite, inside [lo, hi] and, in an integer column, integral (``value_table`` (4, K):
    lo, hi, step, integer); its code is rint(v / step), the yaw's rint(((v + pi) mod 2 pi - pi) /
    step) folded into [-YAW_HALF_TURN, YAW_HALF_TURN) (numba's float mod is numpy's remainder)."""
    n, k = table.shape
    codes = np.zeros((n, k), np.int64)
    for i in range(n):
        for j in range(k):
            v = table[i, j]
            c = np.rint(v / value_table[2, j])
            if not (np.isfinite(v) and value_table[0, j] <= v <= value_table[1, j]
                    and (value_table[3, j] == 0.0 or c == v)):
                return codes, i * k + j
            codes[i, j] = np.int64(c)
        yaw = np.int64(np.rint((np.mod(table[i, yaw_col] + np.pi, 2.0 * np.pi) - np.pi) / YAW_RAD))
        codes[i, yaw_col] = yaw - 2 * YAW_HALF_TURN if yaw >= YAW_HALF_TURN else yaw
    return codes, -1


object_wire.use_compiled(pack_section)
columns.use_compiled(quantize_values)
