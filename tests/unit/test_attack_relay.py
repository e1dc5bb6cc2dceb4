"""The time relay of ``v2i attack`` (v2i.adversary.attack_relay) on real Zenoh sessions on loopback:

    "OBU" --get v2x/rsu/*/time--> [OBU endpoint] attacker queryable -> TimeRelay --get--> [RSU endpoint] "RSU"

The "RSU" answers each (seq, t1) once, as ``rsu_service.time_answers`` makes the real one do.
"""

from __future__ import annotations

import threading
import time

import pytest
import zenoh

from schemas import keys
from schemas.codec import encode
from schemas.messages import TimeRequest
from v2i.adversary.attack_relay import TimeRelay
from v2i.runtime.transport import free_tcp_endpoint, open_session

RSU = "rsu1"
WAIT_S = 5.0


class Lab:
    """An RSU session answering once per query, an attacker bridging the two endpoints, an OBU session."""

    def __init__(self):
        self.rsu_ep, self.obu_ep = free_tcp_endpoint(), free_tcp_endpoint()
        self.rsu = open_session(listen=[self.rsu_ep])
        self.obu = open_session(listen=[self.obu_ep])
        self.sniff = open_session(connect=[self.rsu_ep])
        self.near_obu = open_session(connect=[self.obu_ep])
        self.answered: set[bytes] = set()
        self.entities = [self.rsu.declare_queryable(keys.rsu_time(RSU), self._answer)]
        self.relay: TimeRelay | None = None

    def _answer(self, query) -> None:
        data = query.payload.to_bytes()
        if data in self.answered:
            return  # a repeat: the genuine RSU answers a query once
        self.answered.add(data)
        query.reply(keys.rsu_time(RSU), b"signed:" + data)

    def attack(self, copies: int, delay_ns: int) -> TimeRelay:
        self.relay = TimeRelay(self.sniff, RSU, copies=copies, delay_ns=delay_ns)
        self.entities.append(self.near_obu.declare_queryable(keys.rsu_time(RSU), self.relay.on_query))
        time.sleep(0.3)  # the queryable's declaration reaches the OBU's session
        return self.relay

    def ask(self, seq: int) -> list[tuple[float, bytes]]:
        """One OBU query; (seconds after it was sent, payload) of every reply, once the query is done."""
        replies, done = [], threading.Event()
        t0 = time.monotonic()
        request = encode(TimeRequest(obu_id="ego", seq=seq, t1_ns=time.time_ns()))
        self.obu.get(keys.RSU_TIME_ALL, zenoh.handlers.Callback(
            lambda r: replies.append((time.monotonic() - t0, r.ok.payload.to_bytes())) if r.ok else None, done.set),
            payload=request, timeout=WAIT_S, consolidation=zenoh.ConsolidationMode.NONE)
        assert done.wait(WAIT_S + 1.0)
        return replies

    def close(self) -> None:
        if self.relay is not None:
            self.relay.stop()
        for entity in self.entities:
            entity.undeclare()
        for session in (self.near_obu, self.sniff, self.obu, self.rsu):
            session.close()


@pytest.fixture
def lab():
    lab = Lab()
    try:
        yield lab
    finally:
        lab.close()


def test_each_genuine_reply_comes_back_twice_and_the_query_is_closed(lab):
    relay = lab.attack(copies=2, delay_ns=0)
    for seq in (1, 2, 3):
        replies = lab.ask(seq)
        assert len(replies) == 2 and replies[0][1] == replies[1][1] and replies[0][1].startswith(b"signed:")
    counts = relay.stop()
    assert counts == {"queries": 3, "forwarded": 3, "rsu_replies": 3, "returned": 6}
    assert relay.first_query_ns is not None


def test_a_delayed_request_leg_arrives_late_and_a_repeat_goes_unanswered(lab):
    relay = lab.attack(copies=1, delay_ns=150_000_000)
    (late, reply), = lab.ask(7)
    assert late >= 0.15 and reply.startswith(b"signed:")
    first = lab.ask(8)
    # the same query again (the link's copy won the race): the RSU stays silent, the relay says so
    request = first[0][1][len(b"signed:"):]
    done = threading.Event()
    lab.obu.get(keys.RSU_TIME_ALL, zenoh.handlers.Callback(lambda r: None, done.set), payload=request,
                timeout=WAIT_S, consolidation=zenoh.ConsolidationMode.NONE)
    assert done.wait(WAIT_S + 1.0)
    counts = relay.stop()
    assert counts["queries"] == 3 and counts["rsu_replies"] == 2 and counts["unanswered"] == 1


def test_a_relay_refuses_a_bad_shape_and_drops_what_it_held_when_stopped(lab):
    with pytest.raises(ValueError, match="copy"):
        TimeRelay(lab.sniff, RSU, copies=0)
    with pytest.raises(ValueError, match="copy"):
        TimeRelay(lab.sniff, RSU, delay_ns=-1)
    relay = lab.attack(copies=1, delay_ns=30 * 10**9)  # held far longer than the test
    done = threading.Event()
    lab.obu.get(keys.RSU_TIME_ALL, zenoh.handlers.Callback(lambda r: None, done.set),
                payload=encode(TimeRequest(obu_id="ego", seq=9, t1_ns=time.time_ns())), timeout=60.0)
    deadline = time.monotonic() + WAIT_S
    while relay.snapshot().get("queries", 0) < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    counts = relay.stop()
    assert counts == {"queries": 1, "dropped": 1}
    assert done.wait(WAIT_S)  # the dropped query was closed: the OBU's get ends long before its 60 s timeout
