"""DecodeMemo: one decode per bytes object and key; errors raised again; no id confusion."""

from __future__ import annotations

import pytest

from v2i.offline.decode_memo import DecodeMemo
from schemas.codec import CodecError, MalformedMessage


def test_each_bytes_object_and_key_is_decoded_once() -> None:
    memo, calls = DecodeMemo(size=4), []

    def decode(tag):
        calls.append(tag)
        return {"decoded": tag}

    data = bytes(range(8))
    first = memo.decoded(data, "a", lambda: decode(1))
    assert memo.decoded(data, "a", lambda: decode(2)) is first  # shared by every receiver
    assert memo.decoded(data, "b", lambda: decode(3)) == {"decoded": 3}  # another decoder
    equal_but_other = bytes(range(8))
    assert memo.decoded(equal_but_other, "a", lambda: decode(4)) == {"decoded": 4}  # by identity, not value
    assert calls == [1, 3, 4] and memo.hits == 1


def test_a_codec_error_is_raised_again_for_every_receiver() -> None:
    memo, data = DecodeMemo(), b"\xc1"

    def bad():
        raise MalformedMessage("not msgpack")
    for _ in range(2):
        with pytest.raises(CodecError, match="not msgpack"):
            memo.decoded(data, "a", bad)
    assert memo.hits == 1


def test_oldest_entries_are_dropped() -> None:
    memo, calls = DecodeMemo(size=2), []
    blobs = [bytes([i]) * 4 for i in range(3)]
    for b in blobs:
        memo.decoded(b, "k", lambda b=b: calls.append(b) or b)
    memo.decoded(blobs[0], "k", lambda: calls.append("again") or blobs[0])  # evicted: decoded again
    assert calls[-1] == "again"


def test_an_objects_section_is_unpacked_once_per_exact_content() -> None:
    """DecodeMemo.unpack: unpack_objects' result, shared by equal sections (an RSU's prediction
    list repeats its object list's); a section equal only loosely (1.0 for 1) is decoded on its own
    and refused as unpack_objects refuses it; a refusal is raised every time."""
    import msgpack
    import numpy as np

    from schemas.columns import ObjectColumns
    from schemas.object_wire import pack_objects, unpack_objects

    codes = np.zeros((3, len(ObjectColumns.empty().names)), dtype=np.int64)
    codes[:, 0] = [4, 5, 6]
    codes[:, 2:4] = [[100, -20], [300, 40], [-500, 60]]
    codes[:, 5:7] = [[450, 180]] * 3
    section = msgpack.unpackb(msgpack.packb(pack_objects(ObjectColumns(codes, False))), raw=False)
    memo = DecodeMemo()
    first = memo.unpack(section, False)
    assert first == unpack_objects(section, False)
    assert memo.unpack(list(section), False) is first  # equal content: the same columns
    loose = [float(section[0])] + section[1:]  # == section in Python, not on the wire
    for _ in range(2):
        with pytest.raises(CodecError):
            memo.unpack(loose, False)
    assert memo.unpack(section, True) is not first  # the fused layout is another decode
