"""Each broadcast message decoded once in an offline run (pure).

The offline runner hands one ``bytes`` object to every receiver of a broadcast (an RSU list to
each vehicle, a vehicle's shared list to each peer; a duplicated packet arrives twice), and
each receiver used to decode it again. ``DecodeMemo`` keeps the decoded message, or the
``CodecError``, per bytes object and decoder for the last ``size`` ones: decoded messages are
frozen models whose object columns are read-only arrays, so receivers can share one.

An RSU's prediction list carries the objects of its object list (the same frame's tracks, the
same section bytes): ``unpack`` decodes an objects section once per content (its exact msgpack
bytes, so ``1`` and ``1.0`` stay apart) for the last ``size`` ones.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from typing import Any, TypeVar

import msgpack

from schemas.codec import CodecError
from schemas.columns import ObjectColumns
from schemas.object_wire import unpack_objects

T = TypeVar("T")
DEFAULT_SIZE = 64  # in flight at once: a few messages per RSU and vehicle


class DecodeMemo:
    """``decoded(data, key, decode)``: ``decode()``'s result (or its CodecError, raised again)
    for this very bytes object and ``key`` (the decoder and its arguments)."""

    def __init__(self, size: int = DEFAULT_SIZE):
        self.size = size
        # (id(data), key) -> (data, message or CodecError); data is held so that its id stays its own
        self._entries: OrderedDict[tuple[int, Any], tuple[bytes, Any]] = OrderedDict()
        self._sections: OrderedDict[tuple[bool, bytes], ObjectColumns] = OrderedDict()  # (fused, packed) -> columns
        self.hits = 0

    def decoded(self, data: bytes, key: Any, decode: Callable[[], T]) -> T:
        slot = (id(data), key)
        entry = self._entries.get(slot)
        if entry is not None and entry[0] is data:
            self.hits += 1
            result = entry[1]
        else:
            try:
                result = decode()
            except CodecError as exc:
                result = exc
            self._entries[slot] = (data, result)
            if len(self._entries) > self.size:
                self._entries.popitem(last=False)
        if isinstance(result, CodecError):
            raise result
        return result

    def unpack(self, section: Any, fused: bool) -> ObjectColumns:
        """``object_wire.unpack_objects(section, fused)``, once per section content (a decoded
        msgpack value: packed again, it is its own exact key); a CodecError is not kept."""
        key = (fused, msgpack.packb(section, use_bin_type=True))
        columns = self._sections.get(key)
        if columns is None:
            columns = self._sections[key] = unpack_objects(section, fused)
            if len(self._sections) > self.size:
                self._sections.popitem(last=False)
        return columns
