"""An object list's objects on the wire: per-message column widths, bit-packed rows.

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
(``ObjectColumns.from_codes``: ``InvalidMessage`` naming ``objects.i.column``). Once the kernels are
loaded (``v2i.core.jit.load_kernels``) one compiled loop (``schemas.bit_rows.pack_section``) packs a
section (tests/unit/test_object_wire_paths.py: both paths to the same bytes).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from schemas import bitpack, value_tables
from schemas.columns import COLUMN, ObjectColumns, layout_of
from schemas.errors import InvalidMessage, MalformedMessage
from schemas.limits import MAX_OBJECTS

SECTION_LEN = 7
_WIDTH_BITS, _SCALED, _INDEXED = 0x3F, 0x40, 0x80
MAX_REF = 1 << bitpack.MAX_WIDTH  # |ref| bound: codes stay far inside int64
_YAW_COL = COLUMN["yaw"]
EMPTY_SECTION = (0, 0, b"", (), (), b"", value_tables.NO_TABLES)


def pack_objects(objects: ObjectColumns) -> list[Any]:
    """The msgpack-ready objects section of validated columns (once the kernels are loaded, by one
    compiled loop: ``schemas.bit_rows.pack_section``)."""
    codes, layout = objects.codes, layout_of(objects.fused)
    if len(codes) == 0:
        return list(EMPTY_SECTION)
    if _compiled_section is not None:
        return _section_compiled(codes, layout)
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


def wire_section(objects: ObjectColumns) -> tuple:
    """The msgpack-ready objects section (``pack_objects``), packed once and kept on the columns
    (immutable): a list and a prediction list carrying the same columns share it."""
    section = objects.__dict__.get("wire_section")
    if section is None:
        section = objects.__dict__["wire_section"] = tuple(pack_objects(objects))
    return section


def _section_compiled(codes: np.ndarray, layout) -> list[Any]:
    """``pack_objects``' section by ``schemas.bit_rows.pack_section`` (the same bytes: test_object_wire_paths)."""
    mask, flags, ref, scales, rows, counts, sizes, blob = _compiled_section(codes, np.sort(codes, axis=0),
                                                                            layout.code_table)
    tables = [counts.tolist(), sizes.tobytes(), blob.tobytes()] if len(counts) else list(value_tables.NO_TABLES)
    return [len(codes), mask, flags.tobytes(), ref.tolist(), scales.tolist(), rows.tobytes(), tables]


def object_count(section: Any) -> int:
    """Objects a section declares (0 if it is not a section), before any is decoded."""
    n = section[0] if isinstance(section, list) and section else None
    return n if type(n) is int and n >= 0 else 0


def unpack_objects(section: Any, fused: bool) -> ObjectColumns:
    """Validated columns of an objects section (``MalformedMessage`` for a bad layout). The layout is
    read in plain Python (a section has at most 23 columns: numpy's cost per call would dominate)."""
    layout = layout_of(fused)
    n, present, widths, refs, scales, rows, tables = _fields(section)
    if n > MAX_OBJECTS:
        raise InvalidMessage(f"objects: {n} objects, at most {MAX_OBJECTS} allowed", "objects")
    k = len(layout.specs)
    if present >> k:
        raise MalformedMessage(f"objects: present mask {present:#x} names columns beyond the {k} of this list")
    if n and present & layout.required_mask != layout.required_mask:
        raise MalformedMessage("objects: a required column (id, x, y, length, width) is missing")
    cols = _present_columns(present)
    w, ref, scale, indexed = _descriptors(cols, widths, refs, scales)
    tables = value_tables.ValueTables(tables, np.array(indexed, dtype=bool), n) if any(indexed) or tables != [] \
        else None
    _check_value_bits(w, scale, indexed, tables)
    row_bytes = -(-sum(w) // 8)
    if len(rows) != n * row_bytes:
        raise MalformedMessage(f"objects: rows are {len(rows)} bytes, {n} objects of {row_bytes} bytes expected")
    codes = np.empty((n, k), dtype=np.int64)
    codes[:] = layout.default_codes
    if cols:
        d = bitpack.unpack(rows, n, np.array(w, dtype=np.int64))
        if tables is not None:
            mask = np.array(indexed, dtype=bool)
            d[:, mask] = tables.lookup(d[:, mask])
        codes[:, list(cols)] = d * np.array(scale, dtype=np.int64) + np.array(ref, dtype=np.int64)
    return ObjectColumns.from_codes(codes, fused)


_compiled_section = None  # schemas.bit_rows.pack_section, once loaded (v2i.core.jit.load_kernels)


def use_compiled(pack_section) -> None:
    """From now on ``pack_objects`` builds its section with ``schemas.bit_rows.pack_section``."""
    global _compiled_section
    _compiled_section = pack_section


@lru_cache(maxsize=256)
def _present_columns(present: int) -> tuple[int, ...]:
    """The column indices of a present mask, ascending (a sender's few masks, kept)."""
    return tuple(j for j in range(present.bit_length()) if present >> j & 1)


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


def _descriptors(cols: list[int], widths: bytes, refs: list, scales: list) -> tuple[list, ...]:
    """(F,) width, ref, scale and indexed flag of the F present columns, as lists."""
    if len(widths) != len(cols) or len(refs) != len(cols):
        raise MalformedMessage(f"objects: {len(cols)} present columns but {len(widths)} widths, {len(refs)} refs")
    w = [f & _WIDTH_BITS for f in widths]  # a bytes object iterates as its byte values
    if w and max(w) > bitpack.MAX_WIDTH:
        raise MalformedMessage(f"objects: a column width above {bitpack.MAX_WIDTH} bits")
    scaled = [f & _SCALED != 0 for f in widths]
    if len(scales) != sum(scaled):
        raise MalformedMessage(f"objects: {sum(scaled)} scaled columns but {len(scales)} scales")
    if not _ints_within(refs, -MAX_REF, MAX_REF):
        raise MalformedMessage(f"objects: refs must be integers within +-2^{bitpack.MAX_WIDTH}")
    if not _ints_within(scales, 2, MAX_REF):
        raise MalformedMessage(f"objects: scales must be integers in 2..2^{bitpack.MAX_WIDTH}")
    given = iter(scales)
    scale = [next(given) if x else 1 for x in scaled]
    return w, list(refs), scale, [f & _INDEXED != 0 for f in widths]


def _ints_within(values: list, lo: int, hi: int) -> bool:
    """Every value a plain ``int`` (not a bool, not a float) in [lo, hi] (an empty list: True)."""
    return not values or ({*map(type, values)} == {int} and lo <= min(values) and max(values) <= hi)


def _check_value_bits(w: list[int], scale: list[int], indexed: list[bool],
                      tables: value_tables.ValueTables | None) -> None:
    """No code can overflow: ``ref + d * scale`` with ``d < 2^b`` (``b``: the width, or the bits of an
    indexed column's largest value) and ``b + bits(scale) <= 49`` stays below 2^50."""
    tops = iter(tables.top.tolist() if tables is not None else ())
    for w_j, scale_j, indexed_j in zip(w, scale, indexed):
        b = next(tops).bit_length() if indexed_j else w_j
        if b + scale_j.bit_length() > bitpack.MAX_WIDTH + 1:
            raise MalformedMessage(f"objects: a column's values and scale exceed {bitpack.MAX_WIDTH} bits")
