"""The OBU node on real Zenoh: bad input is rejected and counted, the loop keeps publishing."""

from __future__ import annotations

import queue
import threading
import time
from contextlib import contextmanager

import pytest

from obu_service.config import ObuConfig
from obu_service.node import ObuNode
from rsu_service.config import RsuConfig
from rsu_service.node import RsuNode
from schemas import keys
from schemas.codec import decode, encode
from schemas.messages import FusedObjectList, ObjectList, ObjectListHeader, ObuMetrics
from schemas.transport import free_tcp_endpoint, open_session

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60)]


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


@contextmanager
def running(*nodes):
    """Each node's ``run`` on a thread of its own for the block; every thread has ended after it."""
    stop = threading.Event()
    threads = [threading.Thread(target=n.run, args=(stop,)) for n in nodes]
    for t in threads:
        t.start()
    try:
        yield
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
    start_ns = time.time_ns() + 1_000_000_000
    rsu = RsuNode(RsuConfig(listen=[rsu_ep], start_at_ns=start_ns, duration_s=6.0, clock_offset_ms=250.0))
    obu = ObuNode(ObuConfig(listen=[obu_ep], connect=[rsu_ep], start_at_ns=start_ns, duration_s=6.0))
    outputs, metrics = queue.Queue(), queue.Queue()
    with running(rsu, obu), probe_session(obu_ep) as (probe, entities):
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
        # per-stage latency (telemetry.latency) in the metrics: the RSU's 250 ms clock offset is taken out
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
    """An RSU started 12 s into its scenario (a restart mid-run) publishes at its frame rate from
    now on; the 60 frames it 'missed' are skipped and counted, not sent in a burst."""
    rsu_ep = free_tcp_endpoint()
    rsu = RsuNode(RsuConfig(listen=[rsu_ep], start_at_ns=time.time_ns() - 12_000_000_000, duration_s=30.0))
    stop = threading.Event()
    thread = threading.Thread(target=rsu.run, args=(stop,))
    probe = open_session(connect=[rsu_ep])
    lists = queue.Queue()
    sub = probe.declare_subscriber(keys.rsu_objects("rsu1"), lambda s: lists.put(time.monotonic()))
    try:
        thread.start()
        first = wait_for(lists, lambda t: True, 10.0)
        in_first_second = 1
        while (left_s := first + 1.0 - time.monotonic()) > 0:  # count what arrives within 1 s of the first
            try:
                in_first_second += lists.get(timeout=left_s) < first + 1.0
            except queue.Empty:
                break
        assert in_first_second <= 7, f"{in_first_second} lists in the first second (5 Hz camera)"
        assert rsu.skipped >= 55 and time.monotonic() - first < 5.0
    finally:
        sub.undeclare()
        probe.close()
        stop.set()
        thread.join(10.0)
    assert not thread.is_alive()
