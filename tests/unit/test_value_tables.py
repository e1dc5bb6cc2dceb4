"""Indexed object columns (``schemas.value_tables``): exact round trips, the encoder's choice, and
hostile tables rejected as malformed."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas import bitpack
from schemas.columns import OBJECTS, ObjectColumns
from schemas.errors import MalformedMessage
from schemas.object_wire import pack_objects, unpack_objects
from schemas.value_tables import ValueTables, index_columns

SOME = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
K = len(OBJECTS.specs)
COV_XX = [s.name for s in OBJECTS.specs].index("cov_xx")


def valid_codes(n: int, rng: np.random.Generator, distinct: int = 8) -> np.ndarray:
    """(n, K) valid object codes; cov_xx takes ``distinct`` values spread over a wide range."""
    lo, hi = OBJECTS.code_lo.astype(np.int64), OBJECTS.code_hi.astype(np.int64)
    codes = rng.integers(np.maximum(lo, -3000), np.minimum(hi, 3000) + 1, size=(n, K))
    codes[:, 0] = np.arange(n)  # ids
    codes[:, 1] = 1  # cls: car
    values = np.sort(rng.choice(np.arange(0, 60_000), size=distinct, replace=False))
    codes[:, COV_XX] = rng.choice(values, size=n)
    return codes


@SOME
@given(n=st.integers(1, 300), distinct=st.integers(1, 40), seed=st.integers(0, 2**32 - 1))
def test_sections_round_trip_exactly(n: int, distinct: int, seed: int) -> None:
    codes = ObjectColumns.from_codes(valid_codes(n, np.random.default_rng(seed), distinct)).codes  # yaw wrapped
    decoded = unpack_objects(pack_objects(ObjectColumns(codes.copy(), False)), False)
    np.testing.assert_array_equal(decoded.codes, codes)


@SOME
@given(fields=st.lists(st.lists(st.integers(0, 2**48 - 1) | st.sampled_from([0, 5, 300, 70_000, 2**40]),
                                min_size=3, max_size=3), min_size=1, max_size=80))
def test_index_columns_keeps_every_value(fields: list) -> None:
    """Whatever it indexes, the tables give back the very values, and it narrows only what it indexes."""
    f = np.array(fields, dtype=np.int64)
    f -= f.min(axis=0)  # as object_wire hands them over: each column's smallest is 0
    widths = bitpack.bit_lengths(f.max(axis=0))
    positions, w = f.copy(), widths.copy()
    entry, indexed = index_columns(positions, w)
    assert (w[~indexed] == widths[~indexed]).all() and (w[indexed] < widths[indexed]).all()
    restored = positions.copy()
    if indexed.any():
        assert (positions[:, indexed] < 2 ** w[indexed]).all()
        restored[:, indexed] = ValueTables(entry, indexed, len(f)).lookup(positions[:, indexed])
    np.testing.assert_array_equal(restored, f)


def test_a_column_with_few_wide_values_is_indexed_and_smaller() -> None:
    codes = valid_codes(200, np.random.default_rng(3), distinct=6)
    section = pack_objects(ObjectColumns(codes, False))
    indexed = np.frombuffer(section[2], dtype=np.uint8) & 0x80 != 0
    at = [j for j in range(K) if section[1] >> j & 1].index(COV_XX)  # among the present columns
    assert indexed[at]  # 3 bits per object instead of 16
    assert section[6][0][int(indexed[:at].sum())] == 6  # its table: the 6 values


def test_a_list_with_no_repeated_values_has_no_tables() -> None:
    codes = valid_codes(5, np.random.default_rng(4), distinct=5)
    assert pack_objects(ObjectColumns(codes, False))[6] == []


def indexed_section() -> list:
    section = pack_objects(ObjectColumns(valid_codes(200, np.random.default_rng(5), distinct=6), False))
    assert section[6][0], "the fixture must have a table"
    return section


def with_tables(section: list, tables) -> list:
    return [*section[:6], tables]


def hostile_tables(section: list) -> dict:
    counts, sizes, blob = section[6]
    first = np.frombuffer(blob[:sizes[0] * counts[0]], dtype=f"<u{sizes[0]}")
    return {
        "not_a_list": b"x",
        "short": [counts, sizes],
        "count_zero": [[0, *counts[1:]], sizes, blob],
        "count_above_n": [[201, *counts[1:]], sizes, blob],
        "count_not_int": [[float(counts[0]), *counts[1:]], sizes, blob],
        "missing_table": [counts[1:], sizes[1:], blob[sizes[0] * counts[0]:]],
        "bad_item_size": [counts, bytes([3]) + sizes[1:], blob],
        "blob_too_short": [counts, sizes, blob[:-1]],
        "blob_too_long": [counts, sizes, blob + b"\0"],
        "no_leading_zero": [counts, sizes, (first + 1).astype(first.dtype).tobytes() + blob[first.nbytes:]],
        "not_increasing": [counts, sizes, np.concatenate([first[:1], np.zeros(len(first) - 1, first.dtype)]).tobytes()
                           + blob[first.nbytes:]],
        "huge_gap": [counts, bytes([8]) + sizes[1:],
                     np.r_[0, np.full(len(first) - 1, 2**62)].astype("<u8").tobytes() + blob[first.nbytes:]],
    }


@pytest.mark.parametrize("kind", list(hostile_tables(indexed_section())))
def test_hostile_tables_are_malformed(kind: str) -> None:
    section = indexed_section()
    with pytest.raises(MalformedMessage):
        unpack_objects(with_tables(section, hostile_tables(section)[kind]), False)


def test_a_position_beyond_its_table_is_malformed() -> None:
    section = indexed_section()
    counts, sizes, blob = section[6]
    small = [2, *counts[1:]]  # the first indexed column's positions now point past its table
    first = blob[:sizes[0] * counts[0]]
    with pytest.raises(MalformedMessage, match="beyond"):
        unpack_objects(with_tables(section, [small, sizes, first[:2 * sizes[0]] + blob[len(first):]]), False)
