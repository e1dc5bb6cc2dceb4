"""The OBU's time query leaves with nothing between its t1 stamp and the send but the query itself:
its reply callback runs on the receiving Zenoh thread (``shell.direct_callback``), so ``get`` starts no
Python thread first (0.25-0.3 ms on the uplink leg alone: half of it was a bias of the offset estimate,
docs/clock-sync.md), and the callback only stamps t4 and enqueues."""

from __future__ import annotations

from types import SimpleNamespace

import zenoh

from obu_service.config import ObuConfig
from obu_service.shell import direct_callback
from schemas import keys
from schemas.codec import decode, encode
from schemas.messages import TimeReply, TimeRequest
from v2i.services import obu_node
from v2i.sim.clock import SimClock

START_NS = 1_700_000_000_000_000_000


class Session:
    """Keeps each time query's arguments."""

    def __init__(self):
        self.gets: list[tuple[tuple, dict]] = []

    def get(self, *args, **kwargs) -> None:
        self.gets.append((args, kwargs))


class Payload:
    def __init__(self, data: bytes):
        self.data = data

    def __len__(self) -> int:
        return len(self.data)

    def to_bytes(self) -> bytes:
        return self.data


def node_on(clock: SimClock):
    node = obu_node(ObuConfig(start_at_ns=START_NS, duration_s=1.0), clock=clock)
    node._session = Session()
    return node


def test_a_direct_callback_runs_on_the_receiving_thread():
    def callback(_reply):
        return None

    handler = direct_callback(callback)
    assert isinstance(handler, zenoh.handlers.Callback)
    assert handler.indirect is False  # zenoh-python's default (True) starts a Python thread per get
    assert handler.callback is callback


def test_the_time_query_goes_to_every_rsu_with_a_direct_reply_callback():
    node = node_on(SimClock(START_NS))
    request = TimeRequest(obu_id="ego", seq=7, t1_ns=START_NS)
    node._query_time(request)
    (args, kwargs), = node._session.gets
    assert args[0] == keys.RSU_TIME_ALL
    assert decode(kwargs["payload"], TimeRequest) == request
    handler = args[1]
    assert isinstance(handler, zenoh.handlers.Callback) and handler.indirect is False
    assert handler.callback == node._on_time_reply


def test_the_reply_callback_stamps_t4_on_receipt_and_only_enqueues():
    clock = SimClock(START_NS)
    node = node_on(clock)
    node._query_time(TimeRequest(obu_id="ego", seq=1, t1_ns=START_NS))
    callback = node._session.gets[0][0][1].callback
    reply = TimeReply(rsu_id="rsu-a", seq=1, t1_ns=START_NS, t2_ns=START_NS + 3_000_000, t3_ns=START_NS + 3_050_000)
    clock.t_ns = START_NS + 6_000_000  # t4
    callback(SimpleNamespace(ok=SimpleNamespace(payload=Payload(encode(reply)), key_expr=keys.rsu_time("rsu-a"))))
    assert node.pipeline.clock_offset("rsu-a") is None  # nothing was fed to the estimator on the Zenoh thread
    item = node._intake.get(0.0)
    assert item is not None and item.receive_ns == START_NS + 6_000_000
    assert decode(item.payload, TimeReply) == reply
