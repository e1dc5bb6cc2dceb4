"""The objects section decoder as it was before its descriptors were read in plain Python and its codes
built by one compiled loop (the reference of test_object_wire_paths). Its module docstring follows:

The objects of a message are one msgpack array ``[n, present, widths, refs, scales, rows, tables]``:

- ``n``: object count; ``present``: bitmask over the layout's columns (``schemas.columns``);
  a column left out has its default value in every object (required columns are always there);
- for each present column j, in layout order: one byte of ``widths`` (bits 0-5: width w_j in
  bits, 0..48; bit 6: the column has a scale; bit 7: the column is indexed), an int of ``refs``
  (the column's smallest code) and, if flagged, an int of ``scales`` (the gcd of the codes'
  distances to ``ref``, >= 2);
- ``rows``: each object's fields bit-packed (``schemas.bitpack``) in ``ceil(sum w_j / 8)`` bytes:
  ``d_j = (code_j - ref_j) / scale_j``, or for an indexed column the position of ``d_j`` in its
  table;
- ``tables``: the distinct values of the indexed columns (``schemas.value_tables``).

So each column costs only the bits its spread in this message needs: a constant column costs no
bits per object, a coarser grid than the wire's (sizes every 0.1 m) is divided out by its scale,
and a column with few distinct values spread over a wide range sends ``ceil(log2 U)`` bits per
object plus its table of values, whenever that is smaller.
Decoding checks the layout (``MalformedMessage``) and then every code against its column's range
(``ObjectColumns.from_codes``: ``InvalidMessage`` naming ``objects.i.column``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from schemas import bitpack, value_tables
from schemas.columns import ObjectColumns, layout_of
from schemas.errors import InvalidMessage, MalformedMessage
from schemas.limits import MAX_OBJECTS

SECTION_LEN = 7
_WIDTH_BITS, _SCALED, _INDEXED = 0x3F, 0x40, 0x80
MAX_REF = 1 << bitpack.MAX_WIDTH  # |ref| bound: codes stay far inside int64
EMPTY_SECTION = (0, 0, b"", (), (), b"", value_tables.NO_TABLES)


def pack_objects(objects: ObjectColumns) -> list[Any]:
    """The msgpack-ready objects section of validated columns."""
    codes, layout = objects.codes, layout_of(objects.fused)
    if len(codes) == 0:
        return list(EMPTY_SECTION)
    present = layout.required | (codes != layout.default_codes).any(axis=0)
    cols = np.flatnonzero(present)
    c = codes[:, cols]
    ref = c.min(axis=0)
    span = c - ref
    scale = np.gcd.reduce(span, axis=0)
    scale[scale == 0] = 1
    fields = span // scale
    widths = bitpack.bit_lengths(fields.max(axis=0))
    tables, indexed = value_tables.index_columns(fields, widths)
    flags = np.where(scale > 1, _SCALED, 0) | np.where(indexed, _INDEXED, 0)
    return [len(codes), int(np.left_shift(1, cols).sum()), (widths | flags).astype(np.uint8).tobytes(),
            ref.tolist(), scale[scale > 1].tolist(), bitpack.pack(fields, widths), tables]


def object_count(section: Any) -> int:
    """Objects a section declares (0 if it is not a section), before any is decoded."""
    n = section[0] if isinstance(section, list) and section else None
    return n if type(n) is int and n >= 0 else 0


def unpack_objects(section: Any, fused: bool) -> ObjectColumns:
    """Validated columns of an objects section (``MalformedMessage`` for a bad layout)."""
    layout = layout_of(fused)
    n, present, widths, refs, scales, rows, tables = _fields(section)
    if n > MAX_OBJECTS:
        raise InvalidMessage(f"objects: {n} objects, at most {MAX_OBJECTS} allowed", "objects")
    k = len(layout.specs)
    if present >> k:
        raise MalformedMessage(f"objects: present mask {present:#x} names columns beyond the {k} of this list")
    cols = [j for j in range(k) if present >> j & 1]
    if n and not all(present >> j & 1 for j in np.flatnonzero(layout.required)):
        raise MalformedMessage("objects: a required column (id, x, y, length, width) is missing")
    w, ref, scale, indexed = _descriptors(cols, widths, refs, scales)
    tables = value_tables.ValueTables(tables, indexed, n) if indexed.any() or tables != [] else None
    _check_value_bits(w, scale, indexed, tables)
    if len(rows) != n * bitpack.row_bytes(w):
        raise MalformedMessage(f"objects: rows are {len(rows)} bytes, {n} objects of "
                               f"{bitpack.row_bytes(w)} bytes expected")
    codes = np.empty((n, k), dtype=np.int64)
    codes[:] = layout.default_codes
    if cols:
        d = bitpack.unpack(rows, n, w)
        if tables is not None:
            d[:, indexed] = tables.lookup(d[:, indexed])
        codes[:, cols] = d * scale + ref
    return ObjectColumns.from_codes(codes, fused)


def _fields(section: Any) -> tuple[int, int, bytes, list, list, bytes, list]:
    """The section's seven entries, type-checked."""
    if not isinstance(section, list) or len(section) != SECTION_LEN:
        raise MalformedMessage(f"objects must be a {SECTION_LEN}-entry array [n, present, widths, refs, "
                               f"scales, rows, tables], got {type(section).__name__}")
    n, present, widths, refs, scales, rows, tables = section
    if type(n) is not int or n < 0 or type(present) is not int or present < 0:
        raise MalformedMessage("objects: count and present mask must be non-negative integers")
    if not (isinstance(widths, bytes) and isinstance(rows, bytes) and isinstance(refs, list)
            and isinstance(scales, list)):
        raise MalformedMessage("objects: widths and rows must be bytes, refs and scales arrays")
    return n, present, widths, refs, scales, rows, tables


def _descriptors(cols: list[int], widths: bytes, refs: list, scales: list) -> tuple[np.ndarray, ...]:
    """(F,) width, ref, scale and indexed flag of the F present columns."""
    if len(widths) != len(cols) or len(refs) != len(cols):
        raise MalformedMessage(f"objects: {len(cols)} present columns but {len(widths)} widths, {len(refs)} refs")
    flags = np.frombuffer(widths, dtype=np.uint8)
    w = (flags & _WIDTH_BITS).astype(np.int64)
    scaled = (flags & _SCALED) != 0
    if (w > bitpack.MAX_WIDTH).any():
        raise MalformedMessage(f"objects: a column width above {bitpack.MAX_WIDTH} bits")
    if len(scales) != int(scaled.sum()):
        raise MalformedMessage(f"objects: {int(scaled.sum())} scaled columns but {len(scales)} scales")
    if not all(type(r) is int and -MAX_REF <= r <= MAX_REF for r in refs):
        raise MalformedMessage(f"objects: refs must be integers within +-2^{bitpack.MAX_WIDTH}")
    if not all(type(s) is int and 2 <= s <= MAX_REF for s in scales):
        raise MalformedMessage(f"objects: scales must be integers in 2..2^{bitpack.MAX_WIDTH}")
    scale = np.ones(len(cols), dtype=np.int64)
    scale[scaled] = scales
    return w, np.array(refs, dtype=np.int64), scale, (flags & _INDEXED) != 0


def _check_value_bits(w: np.ndarray, scale: np.ndarray, indexed: np.ndarray,
                      tables: value_tables.ValueTables | None) -> None:
    """No code can overflow: ``ref + d * scale`` with ``d < 2^b`` (``b``: the width, or the bits of an
    indexed column's largest value) and ``b + bits(scale) <= 49`` stays below 2^50."""
    b = w.copy()
    if tables is not None:
        b[indexed] = bitpack.bit_lengths(tables.top)
    if (b + bitpack.bit_lengths(scale) > bitpack.MAX_WIDTH + 1).any():
        raise MalformedMessage(f"objects: a column's values and scale exceed {bitpack.MAX_WIDTH} bits")
