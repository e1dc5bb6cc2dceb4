"""The codec's shortcuts for flat messages: a time request or reply encodes its stored field dict
instead of ``model_dump`` (codec._dumps_as_stored), the same bytes."""

from __future__ import annotations

from typing import Annotated

import msgpack
import numpy as np
import pytest
from pydantic import Field, PlainSerializer, computed_field

from schemas.codec import _dumps_as_stored, decode, encode
from schemas.messages import (MAX_TIME_NS, MIN_TIME_NS, SCHEMA_VERSION, EgoPose, Message, StageLatencyMs,
                              TimeReply, TimeRequest)


def _reference(msg: Message) -> bytes:
    """encode's dict envelope through model_dump (the path before the shortcut)."""
    return msgpack.packb({"v": SCHEMA_VERSION, "t": msg.TYPE, "d": msg.model_dump(mode="python")}, use_bin_type=True)


def _messages(rng: np.random.Generator):
    for _ in range(300):
        t1 = int(rng.integers(MIN_TIME_NS, MAX_TIME_NS - 10**9))
        seq = int(rng.integers(0, 2**63 - 1))
        yield TimeRequest(obu_id=rng.choice(["car-1", "ego", "v_2"]), seq=seq, t1_ns=t1)
        yield TimeReply(rsu_id="rsu-nw", seq=seq, t1_ns=t1, t2_ns=t1 + 5, t3_ns=t1 + int(rng.integers(5, 10**6)))
        yield EgoPose(vehicle_id="car-2", t_ns=t1, x=float(rng.uniform(-1e4, 1e4)), y=float(rng.uniform(-1e4, 1e4)),
                      yaw=float(rng.uniform(-7.0, 7.0)), vx=float(rng.normal(0, 9)), vy=-0.0)
        p = sorted(rng.uniform(0.0, 100.0, 3).tolist())
        yield StageLatencyMs(count=seq, p50=p[0], p95=p[1], p99=p[2])


def test_flat_messages_encode_to_the_model_dump_bytes():
    """Time requests, replies, poses and latencies of random values: the very bytes of the model_dump
    envelope, and they decode to the same message."""
    for msg in _messages(np.random.default_rng(8)):
        assert _dumps_as_stored(type(msg))
        data = encode(msg)
        assert data == _reference(msg)
        assert decode(data, type(msg)) == msg


class _Serialized(Message):
    TYPE = "test_serialized"
    a: Annotated[int, PlainSerializer(lambda v: v + 1)]


class _Excluded(Message):
    TYPE = "test_excluded"
    a: int
    b: int = Field(0, exclude=True)


class _Computed(Message):
    TYPE = "test_computed"
    a: int

    @computed_field
    @property
    def twice(self) -> int:
        return 2 * self.a


class _Optional(Message):
    TYPE = "test_optional"
    a: int | None = None


@pytest.mark.parametrize("msg", [_Serialized(a=1), _Excluded(a=1, b=2), _Computed(a=3), _Optional(a=None)],
                         ids=["serializer", "excluded", "computed", "optional"])
def test_messages_whose_dump_differs_from_their_fields_take_model_dump(msg):
    """A serializer, an excluded or a computed field, an optional one: not flat, encoded through model_dump."""
    assert not _dumps_as_stored(type(msg))
    assert encode(msg) == _reference(msg)
