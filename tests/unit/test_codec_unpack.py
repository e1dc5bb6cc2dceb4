"""``codec._unpack`` (``msgpack.unpackb``, the checked ``Unpacker`` reading only what it refuses) against
``codec._unpack_checked`` alone: the same value, or the same error, for valid, truncated, padded,
oversized-container and random payloads."""

from __future__ import annotations

import msgpack
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas import codec
from schemas.errors import CodecError

MANY = settings(max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
values = st.recursive(st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=8)
                      | st.binary(max_size=8), lambda inner: st.lists(inner, max_size=5)
                      | st.dictionaries(st.text(max_size=4), inner, max_size=4), max_leaves=12)


def outcome(data: bytes, reader):
    """("value", the value packed again: NaN equals NaN, 1 stays apart from 1.0) or (error type, message)."""
    try:
        return "value", msgpack.packb(reader(data, len(data), codec.MAX_MESSAGE_BYTES), use_bin_type=True)
    except CodecError as exc:
        return type(exc), str(exc)


def _same(data: bytes) -> None:
    got, want = outcome(data, codec._unpack), outcome(data, codec._unpack_checked)
    assert got == want, (data, got, want)


@MANY
@given(value=values, cut=st.integers(0, 40), tail=st.binary(max_size=3))
def test_unpack_equals_the_checked_reader(value, cut: int, tail: bytes) -> None:
    data = msgpack.packb(value, use_bin_type=True)
    for payload in (data, data[:max(len(data) - cut, 0)], data + tail):
        _same(payload)


@MANY
@given(data=st.binary(max_size=64))
def test_unpack_equals_the_checked_reader_on_random_bytes(data: bytes) -> None:
    _same(data)


def test_unpack_refuses_what_the_checked_reader_refuses() -> None:
    for data in (b"", b"\x92\x01", msgpack.packb(list(range(codec.MAX_CONTAINER_LEN + 1))), b"\xc1",
                 msgpack.packb({1: 2}), msgpack.ExtType(1, b"x") and msgpack.packb(msgpack.ExtType(1, b"x")), b"\x01\x02"):
        got, want = outcome(data, codec._unpack), outcome(data, codec._unpack_checked)
        assert got == want and got[0] != "value", (data, got)
