"""``object_wire.unpack_objects`` (its layout read in plain Python, its codes built by numpy) against
the decoder it replaced (``legacy_object_wire``): on valid sections, sections with codes out of range
or yaws to wrap, and sections with a damaged entry, the very codes or the very refusal (exception
type, message and field), with either packing path. ``pack_objects`` (numpy, or
``schemas.bit_rows.pack_section`` once the kernels are loaded) against the encoder it replaced: the
very section, indexed columns included."""

from __future__ import annotations

import legacy_object_wire as legacy
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas import object_wire
from schemas.columns import FUSED, OBJECTS, ObjectColumns
from schemas.errors import CodecError

MANY = settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(scope="module", params=["numpy", "compiled"])
def path(request):
    """Run the module's tests with numpy's packing, then with the compiled loop's."""
    from schemas import bit_rows

    saved = object_wire._compiled_section
    object_wire.use_compiled(bit_rows.pack_section if request.param == "compiled" else None)
    yield request.param
    object_wire.use_compiled(saved)


def outcome(fn):
    try:
        return fn(), None
    except CodecError as exc:
        return None, exc


@st.composite
def codes_of(draw, layout, n: int) -> np.ndarray:
    """(n, K) codes: mostly in range, a few at or past an edge; few distinct values at times (tables)."""
    lo, hi = layout.code_lo.astype(np.int64), layout.code_hi.astype(np.int64)
    out = np.empty((n, len(lo)), dtype=np.int64)
    for j in range(len(lo)):
        inside = st.integers(int(max(lo[j], -4000)), int(min(hi[j], 4000)))
        edges = st.sampled_from([int(lo[j]), int(hi[j]), int(lo[j]) - 1, int(hi[j]) + 1, 0])
        few = st.sampled_from([int(max(lo[j], 0)), int(max(lo[j], 0)) + 7_000, int(max(lo[j], 0)) + 31_000])
        cell = draw(st.sampled_from([inside, inside, inside, few, st.one_of(inside, edges)]))
        out[:, j] = draw(st.lists(cell, min_size=n, max_size=n))
    return out


def _damaged(draw, section: list) -> list:
    """The section with one entry changed as a hostile or broken sender might."""
    section = list(section)
    i = draw(st.integers(0, 6))
    if i == 0:
        section[0] = draw(st.sampled_from([section[0] + 1, max(section[0] - 1, 0), -1, 5000, 1.0]))
    elif i == 1:
        section[1] = draw(st.sampled_from([section[1] ^ 1, section[1] | 1 << 23, section[1] | 1 << 30, 0]))
    elif i == 2 and section[2]:
        raw = bytearray(section[2])
        raw[draw(st.integers(0, len(raw) - 1))] ^= draw(st.sampled_from([0x01, 0x3F, 0x40, 0x80, 0x31]))
        section[2] = bytes(raw)
    elif i == 3 and section[3]:
        refs = list(section[3])
        refs[draw(st.integers(0, len(refs) - 1))] = draw(st.sampled_from([True, 1.5, 2**49, -(2**49), 7, -900000]))
        section[3] = refs
    elif i == 4:
        section[4] = draw(st.sampled_from([[], [1], [2**49], [3, 3], [True], list(section[4]) + [5]]))
    elif i == 5 and section[5]:
        raw = bytearray(section[5])
        raw[draw(st.integers(0, len(raw) - 1))] ^= draw(st.integers(1, 255))
        section[5] = bytes(raw) if draw(st.booleans()) else bytes(raw) + b"\0"
    elif i == 6:
        tables = section[6]
        section[6] = draw(st.sampled_from([[], [[1], b"\x01", b"\0"], [[9], b"\x02", b"\0"]] + (
            [[tables[0], tables[1], tables[2][:-1]], [[c + 1 for c in tables[0]], tables[1], tables[2]]]
            if tables else [])))
    return section


@st.composite
def sections(draw):
    fused = draw(st.booleans())
    layout = FUSED if fused else OBJECTS
    n = draw(st.sampled_from([0, 1, 2, 5, 8, 40]))
    codes = draw(codes_of(layout, n))
    section = list(object_wire.pack_objects(ObjectColumns(codes, fused)))  # raw codes: the decoder judges
    if draw(st.integers(0, 2)) == 0:
        section = _damaged(draw, section)
    return section, fused


@MANY
@given(case=sections())
def test_unpack_objects_equals_the_decoder_it_replaced(path, case) -> None:
    section, fused = case
    want, want_err = outcome(lambda: legacy.unpack_objects(section, fused))
    got, got_err = outcome(lambda: object_wire.unpack_objects(section, fused))
    assert (want_err is None) == (got_err is None), (want_err, got_err)
    if want_err is not None:
        assert (type(got_err), str(got_err), got_err.reason, getattr(got_err, "field", None)) == \
            (type(want_err), str(want_err), want_err.reason, getattr(want_err, "field", None))
        return
    assert got.fused == want.fused and got.codes.dtype == want.codes.dtype
    np.testing.assert_array_equal(got.codes, want.codes)
    assert not got.codes.flags.writeable


@MANY
@given(fused=st.booleans(), n=st.sampled_from([1, 2, 3, 6, 30, 200]), distinct=st.integers(1, 12),
       wide=st.sampled_from([300, 70_000, 2**33]), seed=st.integers(0, 2**32 - 1))
def test_pack_objects_equals_the_encoder_it_replaced(path, fused: bool, n: int, distinct: int, wide: int,
                                                       seed: int) -> None:
    """Codes with some columns constant or at their default, some on a coarse grid (a scale), some with
    few distinct values far apart (indexed when that is smaller, with 1-, 2-, 4- and 8-byte gaps)."""
    layout = FUSED if fused else OBJECTS
    rng = np.random.default_rng(seed)
    lo, hi = layout.code_lo.astype(np.int64), layout.code_hi.astype(np.int64)
    codes = rng.integers(np.maximum(lo, -3000), np.minimum(hi, 3000) + 1, size=(n, len(lo)))
    for j in rng.choice(len(lo), size=6, replace=False):
        kind = rng.integers(0, 4)
        if kind == 0:
            codes[:, j] = layout.default_codes[j]
        elif kind == 1:
            codes[:, j] = codes[0, j]
        elif kind == 2:
            codes[:, j] = np.maximum(lo[j], 0) + 20 * rng.integers(0, 50, size=n)
        else:
            values = np.maximum(lo[j], 0) + np.sort(rng.choice(wide, size=distinct, replace=False))
            codes[:, j] = np.minimum(rng.choice(values, size=n), hi[j])
    columns = ObjectColumns(codes, fused)  # raw codes: the encoder packs what it is given
    assert object_wire.pack_objects(columns) == legacy.pack_objects(columns)


def test_the_compiled_path_is_the_one_the_services_use() -> None:
    """Once the kernels are loaded (services, v2i eval), ``pack_objects`` packs with the loop."""
    from v2i.core.jit import load_kernels
    from schemas import bit_rows

    load_kernels(("schemas.bit_rows",))
    assert object_wire._compiled_section is bit_rows.pack_section
