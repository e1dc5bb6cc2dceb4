"""The object-level OBU's loop (``ObuNode._loop``) on a simulated clock, no Zenoh: its timed events are
typed values fired in due order (at one time by rank), every simulated capture makes one cycle, and
the run's end stops it."""

from __future__ import annotations

import threading

from obu_service.config import ObuConfig
from obu_service.node import Capture, Deadline, End, Fuse, Sync
from v2i.services import obu_node
from v2i.sim.clock import SimClock

START_NS = 1_700_000_000_000_000_000


class Sink:
    def __init__(self):
        self.puts = 0

    def put(self, _data: bytes) -> None:
        self.puts += 1


class Session:
    """Takes the time queries (no RSU answers)."""

    def __init__(self):
        self.queries = 0

    def get(self, *_args, **_kwargs) -> None:
        self.queries += 1


def node_on(clock: SimClock, duration_s: float):
    """A --source sim node without Zenoh whose fired events are recorded (due time, event); no input comes,
    so the clock runs on to each next event."""
    node = obu_node(ObuConfig(start_at_ns=START_NS, duration_s=duration_s, sync_rate_hz=5.0), clock=clock)
    node._pub = {name: Sink() for name in ("objects", "metrics", "pose", "planning")}
    node._session = Session()
    node.fired = []
    fire = node._fire

    def recorded(due_ns, event):
        node.fired.append((due_ns, event))
        fire(due_ns, event)

    def idle(timeout_s: float):
        clock.t_ns += max(1, round(timeout_s * 1e9))

    node._fire, node._intake.get = recorded, idle
    return node


def test_events_fire_in_due_order_and_each_capture_makes_a_cycle():
    node = node_on(SimClock(START_NS), 1.0)
    node._schedule()
    node._loop(threading.Event())  # returns at End
    fired = node.fired
    due = [t for t, _ in fired]
    assert due == sorted(due)
    captures = [t for t, e in fired if isinstance(e, Capture)]
    fuses = [(t, e) for t, e in fired if isinstance(e, Fuse)]
    assert len(captures) == len(fuses) == node.pipeline.cycles == node._pub["objects"].puts == 10
    delay_ns = round(node.config.fuse_delay_ms * 1e6)
    assert [t for t, _ in fuses] == [c + delay_ns for c in captures]
    assert all(e.frame.capture_ns == c for (_, e), c in zip(fuses, captures))
    syncs = sum(isinstance(e, Sync) for _, e in fired)
    assert syncs == node._session.queries == 5
    assert any(isinstance(e, Deadline) for _, e in fired) and not any(isinstance(e, End) for _, e in fired)


def test_at_one_time_events_fire_by_rank_then_as_pushed():
    node = node_on(SimClock(START_NS), 1.0)
    for event in (Sync(), End(), Capture(), Deadline(), Sync()):
        node._at(START_NS + 1_000, event)
    node._loop(threading.Event())  # the capture's Fuse comes after End
    assert [type(e) for _, e in node.fired] == [Deadline, Capture, Sync, Sync]
    assert node._session.queries == 2
