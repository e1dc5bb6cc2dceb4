"""The OBU node on real Zenoh: bad input is rejected and counted, the loop keeps publishing.

The nodes run in this process with the start handshake (``--await-start``): each says it is ready
(session open, declared), and time zero is picked once every one is (``running``), so a busy
machine only starts them later."""

from __future__ import annotations

import queue
import threading
import time
from contextlib import contextmanager

import pytest

from v2i.orchestration.children import READY_TIMEOUT_S, START_LEAD_S
from obu_service.config import ObuConfig
from rsu_service.config import RsuConfig
from schemas import keys
from schemas.codec import decode, encode
from schemas.messages import FusedObjectList, ObjectList, ObjectListHeader, ObuMetrics
from v2i.runtime.transport import free_tcp_endpoint, open_session
from v2i.services import obu_node, rsu_node

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60 + READY_TIMEOUT_S)]
RUN_S = 60.0  # the nodes' run from time zero: longer than every wait of a test; its block's end stops them


def wait_for(q: queue.Queue, predicate, timeout_s: float):
    """The first item of q satisfying predicate, or fail after timeout_s."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            item = q.get(timeout=0.05)
        except queue.Empty:
            continue
        if predicate(item):
            return item
    pytest.fail("expected message did not arrive in time")


class StartGate:
    """Time zero for nodes run in this process with ``await_start`` (the start line's part): each
    node's ``run`` calls it after its ready line; once all ``parties`` have, time zero is now +
    ``lead_s`` (negative: a time zero that has passed, a restart mid-run) and every one gets it."""

    def __init__(self, parties: int, lead_s: float = START_LEAD_S):
        self.parties, self.lead_s = parties, lead_s
        self.start_ns: int | None = None
        self.started = threading.Event()  # set once time zero is picked
        self._arrived = 0
        self._lock = threading.Lock()

        self.ready = threading.Event()  # set once every node is ready
        self.auto = True  # time zero as soon as every node is ready (False: when ``start`` is called)

    def __call__(self, _service: str, stop: threading.Event) -> int | None:
        with self._lock:
            self._arrived += 1
            if self._arrived == self.parties:
                self.ready.set()
                if self.auto:
                    self.start()
        while not self.started.wait(0.05):
            if stop.is_set():
                return None
        return self.start_ns

    def start(self) -> int:
        """Time zero now + ``lead_s`` for every node (those not ready yet get it when they are)."""
        self.start_ns = time.time_ns() + round(self.lead_s * 1e9)
        self.started.set()
        return self.start_ns


@contextmanager
def running(*nodes, lead_s: float = START_LEAD_S, start: bool = True):
    """Each node's ``run`` on a thread of its own for the block, which gets their ``StartGate``: the
    nodes built with ``await_start`` are all ready (at most ``READY_TIMEOUT_S``) and, with ``start``,
    have time zero ``gate.start_ns`` (without: the block calls ``gate.start()``, e.g. once it has
    subscribed); every thread has ended after the block."""
    stop = threading.Event()
    gate = StartGate(sum(bool(n.config.await_start) for n in nodes), lead_s)
    gate.auto = start
    threads = [threading.Thread(target=n.run, args=(stop, gate) if n.config.await_start else (stop,)) for n in nodes]
    for t in threads:
        t.start()
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while gate.parties and not (gate.started if start else gate.ready).wait(0.05):
            assert all(t.is_alive() for t in threads), "a node's run ended before every node was ready"
            assert time.monotonic() < deadline, f"the nodes were not ready within {READY_TIMEOUT_S:g} s"
        yield gate
    finally:
        stop.set()
        for t in threads:
            t.join(10.0)
    assert not any(t.is_alive() for t in threads)


@contextmanager
def probe_session(endpoint: str):
    """A session connected to ``endpoint`` and the list its entities go in; all undeclared, then closed."""
    session, entities = open_session(connect=[endpoint]), []
    try:
        yield session, entities
    finally:
        for entity in entities:
            entity.undeclare()
        session.close()


def test_obu_rejects_garbage_keeps_publishing_and_syncs_with_a_direct_rsu():
    rsu_ep, obu_ep = free_tcp_endpoint(), free_tcp_endpoint()
    rsu = rsu_node(RsuConfig(listen=[rsu_ep], await_start=True, duration_s=RUN_S, clock_offset_ms=250.0))
    obu = obu_node(ObuConfig(listen=[obu_ep], connect=[rsu_ep], await_start=True, duration_s=RUN_S))
    outputs, metrics = queue.Queue(), queue.Queue()
    with running(rsu, obu) as gate, probe_session(obu_ep) as (probe, entities):
        start_ns = gate.start_ns
        entities += [
            probe.declare_subscriber(keys.obu_objects("ego"), lambda s: outputs.put(decode(s.payload.to_bytes(), FusedObjectList))),
            probe.declare_subscriber(keys.obu_metrics("ego"), lambda s: metrics.put(decode(s.payload.to_bytes(), ObuMetrics)))]
        wait_for(outputs, lambda m: True, 10.0)
        valid_but_absurd = ObjectList(header=ObjectListHeader(rsu_id="evil", seq=1, capture_time_ns=start_ns,
                                                              publish_time_ns=start_ns))
        for payload in (b"\x00garbage", encode(valid_but_absurd)[:-3], b"\x81\xa1v\x63"):
            probe.put(keys.rsu_objects("evil"), payload)
        m = wait_for(metrics, lambda m: sum(m.rejected.values()) >= 3 and any(
            r.rsu_id == "rsu1" and r.clock_offset_ns is not None for r in m.rsus), 10.0)
        offset = next(r for r in m.rsus if r.rsu_id == "rsu1").clock_offset_ns
        assert abs(offset - 250_000_000) < 5_000_000  # direct loopback: error well under 5 ms
        fused = wait_for(outputs, lambda o: o.mode == "inter", 10.0)
        assert fused.cycle_time_ns >= start_ns
        # per-stage latency (v2i.telemetry.latency) in the metrics: the RSU's 250 ms clock offset is taken out
        m = wait_for(metrics, lambda m: {"rsu_to_obu", "queue", "decode", "ingest", "fuse", "publish"} <= set(m.latency_ms),
                     10.0)
        for stage, q in m.latency_ms.items():
            assert q.count >= 1 and 0.0 <= q.p50 <= q.p95 <= q.p99 < 100.0, (stage, q)
        assert m.latency_ms["rsu_to_obu"].p50 < 50.0  # direct loopback: a few ms, not the offset
        assert m.latency_ms["fuse"].count <= m.cycles
        assert obu.last_metrics is not None and obu.latency.histogram("fuse")[2] >= m.latency_ms["fuse"].count
        rsu_stages = set(rsu.last_metrics.latency_ms)
        assert {"detect", "track", "message", "encode", "put", "stamp_to_put"} <= rsu_stages


def test_a_restarted_rsu_publishes_only_what_is_current():
    """An RSU started 12 s into its scenario (a restart mid-run: its start line names a time zero
    12 s ago) publishes at its frame rate from now on; the 60 frames it 'missed' are skipped and
    counted, not sent in a burst."""
    rsu_ep = free_tcp_endpoint()
    rsu = rsu_node(RsuConfig(listen=[rsu_ep], await_start=True, duration_s=30.0))
    lists = queue.Queue()
    with running(rsu, lead_s=-12.0, start=False) as gate, probe_session(rsu_ep) as (probe, entities):
        entities.append(probe.declare_subscriber(keys.rsu_objects("rsu1"), lambda s: lists.put(time.monotonic())))
        # the RSU's liveliness token answers over the same link, after the subscription: the RSU knows it now
        replies = probe.liveliness().get(keys.rsu_alive("rsu1"), timeout=10.0)
        assert any(r.ok is not None for r in replies), "no route to the RSU"
        gate.start()
        first = wait_for(lists, lambda t: True, 10.0)  # at once: the frame of now is current
        in_first_second = 1
        while (left_s := first + 1.0 - time.monotonic()) > 0:  # count what arrives within 1 s of the first
            try:
                in_first_second += lists.get(timeout=left_s) < first + 1.0
            except queue.Empty:
                break
        assert in_first_second <= 7, f"{in_first_second} lists in the first second (5 Hz camera)"
        assert rsu.skipped >= 55 and time.monotonic() - first < 5.0
