"""``ValueTables`` reads a few values in Python ints (``_read_small``) and many with numpy: both give the
same arrays, or refuse with the same error, on valid tables and on damaged ones (hostile input)."""

import numpy as np

from schemas import value_tables
from schemas.errors import MalformedMessage
from schemas.value_tables import ValueTables, index_columns


def _outcome(entry, indexed: np.ndarray, n: int):
    try:
        tables = ValueTables(entry, indexed, n)
    except MalformedMessage as exc:
        return type(exc), str(exc)
    return [(a.dtype.str, a.shape, a.tobytes()) for a in (tables.counts, tables.starts, tables.sums, tables.top)]


def _both(entry, indexed: np.ndarray, n: int, monkeypatch):
    monkeypatch.setattr(value_tables, "SMALL_TABLES", 10**9)
    small = _outcome(entry, indexed, n)
    monkeypatch.setattr(value_tables, "SMALL_TABLES", -1)
    large = _outcome(entry, indexed, n)
    return small, large


def _entries(rng: np.random.Generator):
    """Valid tables (index_columns of fields with few wide values), then each damaged several ways."""
    for _ in range(150):
        n, f = int(rng.integers(1, 40)), int(rng.integers(1, 5))
        choices = rng.choice([0, 1, 7, 255, 256, 70_000, 2**33, 2**48 - 1], size=(4, f))
        fields = np.stack([rng.choice(choices[:, j], n) for j in range(f)], axis=1).astype(np.int64)
        fields -= fields.min(axis=0)
        widths = np.array([int(v).bit_length() for v in fields.max(axis=0)], dtype=np.int64)
        entry, indexed = index_columns(fields, widths)
        if not indexed.any():
            continue
        yield entry, indexed, n
        counts, sizes, blob = entry
        yield [counts, sizes, blob[:-1]], indexed, n  # short blob
        yield [counts, sizes, blob + b"\x00"], indexed, n  # long blob
        yield [[c + 1 for c in counts], sizes, blob], indexed, n  # counts beyond the blob
        yield [counts, bytes(8 for _ in sizes), blob], indexed, n  # other item sizes
        for _ in range(4):  # a byte changed: a zero gap inside, a gap too wide, a table not increasing
            damaged = bytearray(blob)
            damaged[int(rng.integers(len(damaged)))] = int(rng.choice([0, 1, 255]))
            yield [counts, sizes, bytes(damaged)], indexed, n
        if len(sizes) and sizes[0] == 8:  # gaps at and past 2^48
            yield [counts, sizes, b"\x00" * 8 + (2**48).to_bytes(8, "little") + blob[16:]], indexed, n
    yield [[2, 1], bytes([8, 8]), b"\x00" * 8 + (2**48 - 1).to_bytes(8, "little") + b"\x00" * 8], np.array([1, 1], bool), 4


def test_small_tables_read_as_numpy_reads_them(monkeypatch):
    rng = np.random.default_rng(9)
    refused = accepted = 0
    for entry, indexed, n in _entries(rng):
        small, large = _both(entry, indexed, n, monkeypatch)
        assert small == large, (entry, small, large)
        refused += isinstance(small, tuple)
        accepted += isinstance(small, list)
    assert refused > 200 and accepted > 150
