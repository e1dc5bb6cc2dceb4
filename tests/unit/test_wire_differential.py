"""The columnar decoder against today's model-based one (``legacy_codec``), and the bit packer
against Python integers.

Differential: the same object codes and header fields, valid or not, sent once in the old wire
(fixed-width little-endian columns, each object validated by its pydantic model) and once in
the new one (per-message widths, validated as arrays), must be accepted by both with the same
values or rejected by both for the same reason (and the same field where only one is wrong).
"""

from __future__ import annotations

import legacy_codec as old
import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas import bitpack
from schemas.codec import LIST_TAGS, decode
from schemas.columns import FUSED, OBJECTS, ObjectColumns
from schemas.errors import CodecError
from schemas.messages import SCHEMA_VERSION, FusedObjectList, ObjectList
from schemas.object_wire import pack_objects
from schemas.wire_view import SECTION_KEYS, pack_view

T0 = 1_700_000_000 * 10**9
MANY = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])

BAD_HEADER = {"rsu_id": ["", "a/b"], "seq": [-1], "capture_time_ns": [0], "publish_time_ns": [T0 - 1],
              "frame_id": ["x" * 65], "prediction_ns": [-1, 10**11]}
BAD_FUSED = {"vehicle_id": ["*"], "seq": [-5], "cycle_time_ns": [1], "mode": ["m" * 33], "ego_x": [2e6]}


@st.composite
def codes_of(draw, columns, n: int, layout) -> np.ndarray:
    """(n, K) codes inside each old column's dtype: mostly in the model's range, some edges."""
    out = np.empty((n, len(columns)), dtype=np.int64)
    for j, col in enumerate(columns):
        lo, hi = col.bounds
        clo, chi = max(lo, int(layout.code_lo[j])), min(hi, int(layout.code_hi[j]))
        edges = sorted({lo, hi, clo, chi, max(lo, clo - 1), min(hi, chi + 1), 0 if lo <= 0 <= hi else lo})
        inside = st.integers(clo, min(chi, clo + 5000)) | st.integers(max(clo, chi - 5000), chi)
        cell = st.one_of(inside, inside, inside, st.sampled_from(edges)) if draw(st.integers(0, 3)) == 0 else inside
        out[:, j] = draw(st.lists(cell, min_size=n, max_size=n))
    return out


@st.composite
def cases(draw):
    fused = draw(st.booleans())
    columns, layout = (old.FUSED_OBJECT_COLUMNS, FUSED) if fused else (old.OBJECT_COLUMNS, OBJECTS)
    n = draw(st.integers(0, 6))
    codes = draw(codes_of(columns, n, layout))
    if fused:
        fields = {"vehicle_id": "car-1", "seq": 3, "cycle_time_ns": T0, "publish_time_ns": T0 + 10**7,
                  "mode": "intra", "ego_x": 1.25}
        bad = BAD_FUSED
    else:
        fields = {"header": {"rsu_id": "rsu-1", "seq": 9, "capture_time_ns": T0, "publish_time_ns": T0 + 10**8,
                             "sensor": "cam", "prediction_ns": 5 * 10**7}}
        bad = BAD_HEADER
    if draw(st.integers(0, 4)) == 0:
        key = draw(st.sampled_from(sorted(bad)))
        (fields if fused else fields["header"])[key] = draw(st.sampled_from(bad[key]))
    return fused, fields, codes


def old_bytes(fused: bool, fields: dict, codes: np.ndarray) -> bytes:
    columns = old.FUSED_OBJECT_COLUMNS if fused else old.OBJECT_COLUMNS
    objects = {"n": len(codes)} | {c.name: codes[:, j].astype(c.dtype).tobytes() for j, c in enumerate(columns)}
    model = FusedObjectList if fused else ObjectList
    return msgpack.packb({"v": SCHEMA_VERSION, "t": model.TYPE, "d": fields | {"objects": objects}}, use_bin_type=True)


def new_bytes(fused: bool, fields: dict, codes: np.ndarray) -> bytes:
    section = pack_objects(ObjectColumns(codes.copy(), fused))  # raw codes, unchecked: the decoder judges
    model = FusedObjectList if fused else ObjectList
    return pack_view({"v": SCHEMA_VERSION, "t": LIST_TAGS[model.TYPE],
                      "d": fields | {"objects": dict(zip(SECTION_KEYS, section))}})


def outcome(fn):
    try:
        return fn(), None
    except CodecError as exc:
        return None, exc


@MANY
@given(cases())
def test_new_decoder_accepts_exactly_what_the_old_models_accept(case) -> None:
    fused, fields, codes = case
    old_msg, old_err = outcome(lambda: old.decode(old_bytes(fused, fields, codes),
                                                  old.FusedObjectList if fused else old.ObjectList))
    new_msg, new_err = outcome(lambda: decode(new_bytes(fused, fields, codes), FusedObjectList if fused else ObjectList))
    assert (old_err is None) == (new_err is None), (old_err, new_err)
    if old_err is not None:
        assert old_err.reason == new_err.reason
        header_ok = not any(str(err.field).startswith(("header", "vehicle_id", "seq", "cycle", "mode", "ego"))
                            for err in (old_err, new_err))
        if header_ok:  # the old decoder names the header first when both are wrong; alone, both name the same
            assert old_err.field == new_err.field, (old_err, new_err)
        return
    names = new_msg.objects.names
    table = np.array([[float(getattr(o, k)) for k in names] for o in old_msg.objects]).reshape(len(codes), len(names))
    assert np.array_equal(table, new_msg.objects.values)  # exact, not close
    for name, field in type(new_msg).model_fields.items():
        if name == "objects":
            continue
        # a field the old models did not have (mode_reason): the old wire leaves it at its default
        expected = getattr(old_msg, name) if name in type(old_msg).model_fields else field.default
        assert getattr(new_msg, name) == expected


@MANY
@given(st.data())
def test_bit_packing_equals_python_integers(data) -> None:
    """Both packers (numpy's, and the compiled loop of schemas.bit_rows.pack_section) and numpy's unpacking
    against int.to_bytes."""
    from schemas.bit_rows import _packed

    k = data.draw(st.integers(1, 24))
    widths = np.array(data.draw(st.lists(st.integers(0, bitpack.MAX_WIDTH), min_size=k, max_size=k)), np.int64)
    n = data.draw(st.integers(0, 5))
    fields = np.array([[data.draw(st.integers(0, (1 << int(w)) - 1)) for w in widths] for _ in range(n)],
                      dtype=np.int64).reshape(n, k)
    starts = np.concatenate([[0], np.cumsum(widths)[:-1]])
    row_bytes = -(-int(widths.sum()) // 8)
    expected = b"".join(sum(int(v) << int(s) for v, s in zip(row, starts)).to_bytes(row_bytes, "little")
                        for row in fields)
    assert bitpack.pack(fields, widths) == expected
    assert _packed(fields, widths, row_bytes).tobytes() == expected
    assert np.array_equal(bitpack.unpack(expected, n, widths), fields)
    for wrong in ([expected[:-1]] if n and row_bytes else []) + [expected + b"\0"]:  # a byte short or over
        with pytest.raises(ValueError):  # refused: never read past the bytes
            bitpack.unpack(wrong, n, widths)


def test_bit_lengths_equal_python() -> None:
    values = np.array([0, 1, 2, 3, 4, 255, 256, 2**32 - 1, 2**32, 2**48 - 1, 2**62], np.int64)
    assert bitpack.bit_lengths(values).tolist() == [int(v).bit_length() for v in values]
