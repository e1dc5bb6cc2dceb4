"""Open inputs on real Zenoh and real processes: an outside publisher feeds ``v2i obu --source
zenoh``; ``v2i world`` feeds ``v2i rsu --source zenoh``. Explicit tcp/127.0.0.1 endpoints,
scouting off (v2i.runtime.transport), deadlines rather than sleeps, every process stopped."""

from __future__ import annotations

import queue
import sys
import time
from pathlib import Path

import pytest

from v2i.orchestration.children import READY_TIMEOUT_S, Child, start_all, wait_ready
from schemas import keys
from schemas.codec import decode
from schemas.messages import SOURCE_VEHICLE, FusedObjectList, ObjectList, ObuMetrics, RsuMetrics
from v2i.runtime.transport import free_tcp_endpoint, open_session

pytestmark = [pytest.mark.integration, pytest.mark.timeout(READY_TIMEOUT_S + 60)]

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "external_publisher.py"
V2I = [sys.executable, "-m", "v2i"]


def collect(q: queue.Queue, predicate, timeout_s: float):
    """The first item of ``q`` satisfying ``predicate``; fails after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            item = q.get(timeout=0.05)
        except queue.Empty:
            continue
        if predicate(item):
            return item
    pytest.fail("the expected message did not arrive in time")


class Probe:
    """A Zenoh session decoding what arrives on some keys into queues."""

    def __init__(self, endpoint: str, subscriptions: dict[str, type]):
        self.session = open_session(connect=[endpoint])
        self.queues = {key: queue.Queue() for key in subscriptions}
        self.subs = [self.session.declare_subscriber(
            key, lambda s, key=key, model=model: self.queues[key].put(decode(s.payload.to_bytes(), model)))
            for key, model in subscriptions.items()]

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.session.close()




def test_external_publisher_objects_come_out_of_the_obus_fused_output():
    obu_ep = free_tcp_endpoint()
    children = [Child("obu", [*V2I, "obu", "--source", "zenoh", "--listen", obu_ep, "--await-start", "--duration", "60"])]
    probe = None
    try:
        wait_ready(children)
        probe = Probe(obu_ep, {keys.obu_objects("ego"): FusedObjectList, keys.obu_metrics("ego"): ObuMetrics})
        start_all(children)
        children.append(Child("publisher", [sys.executable, str(EXAMPLE), "--connect", obu_ep, "--duration", "20"]))
        outputs, metrics = probe.queues[keys.obu_objects("ego")], probe.queues[keys.obu_metrics("ego")]

        def has_the_car(out: FusedObjectList) -> bool:
            return any(abs(o.x - 20.0) < 0.5 and abs(o.y - 3.5) < 0.5 and o.sources & SOURCE_VEHICLE
                       for o in out.objects)

        # the publisher is a process that prints no ready line: its start-up (an interpreter importing zenoh) is
        # given the bound every service gets to be ready
        first = collect(outputs, has_the_car, READY_TIMEOUT_S)
        for _ in range(10):  # ten more cycles in a row carry it, on time, with the publisher's pose
            out = collect(outputs, lambda o, t_ns=first.cycle_time_ns: o.cycle_time_ns > t_ns, 5.0)
            assert has_the_car(out) and out.publish_time_ns - out.cycle_time_ns < 100_000_000
            assert out.ego_y == 0.0 and out.ego_x > 0.0
            first = out
        m = collect(metrics, lambda m: m.cycles >= 10, 5.0)
        assert m.output_deadline_misses == 0
        assert not {r for r in m.rejected if r.startswith("input_") and r != "input_missing"}
    finally:
        if probe is not None:
            probe.close()
        for child in reversed(children):
            child.stop()


def test_world_feeds_an_rsu_that_publishes_object_lists_and_refuses_bad_inputs():
    rsu_ep = free_tcp_endpoint()
    common = ["--await-start", "--duration", "60", "--seed", "3"]  # the children are stopped when the test is done
    children = [Child("rsu", [*V2I, "rsu", "--source", "zenoh", "--listen", rsu_ep, *common]),
                Child("world", [*V2I, "world", "--connect", rsu_ep, "--rsu-id", "rsu1", *common])]
    probe = None
    try:
        wait_ready(children)
        probe = Probe(rsu_ep, {keys.rsu_objects("rsu1"): ObjectList, keys.rsu_metrics("rsu1"): RsuMetrics})
        start_ns = start_all(children)
        lists, metrics = probe.queues[keys.rsu_objects("rsu1")], probe.queues[keys.rsu_metrics("rsu1")]
        # the world's cars, tracked by the RSU: confirmed after a few of its 5 Hz frames from time zero
        tracked = collect(lists, lambda m: len(m.objects) > 0, 12.0)
        assert tracked.header.rsu_id == "rsu1" and tracked.header.capture_time_ns >= start_ns
        assert tracked.header.publish_time_ns - tracked.header.capture_time_ns < 300_000_000
        for payload in (b"\x00garbage", b"\x93\x01\x02"):  # refused and counted, the RSU goes on
            probe.session.put(keys.sensor_rsu_objects("rsu1"), payload)
        m = collect(metrics, lambda m: m.rejected.get("input_malformed", 0) >= 2, 5.0)
        later = collect(lists, lambda x: x.header.seq > tracked.header.seq + 3, 5.0)
        assert later.header.capture_time_ns > tracked.header.capture_time_ns and m.published > 0
    finally:
        if probe is not None:
            probe.close()
        for child in reversed(children):
            child.stop()
