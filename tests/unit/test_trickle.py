"""The TCP trickle (``v2i.adversary.trickle``): its schedule, and its sockets against a local listener."""

import socket
import threading
import time

import pytest

from v2i.adversary.trickle import TrickleCounts, TricklePlan, TrickleSpec, parse_endpoint, run_trickle


def _ticks(spec: TrickleSpec, start_s: float = 100.0) -> list[tuple[float, int]]:
    plan, ticks = TricklePlan(spec, start_s), []
    while (due := plan.next_due()) is not None:
        ticks.append(due)
        plan.done(due[1], due[0])
    return ticks


def test_the_plan_spreads_the_sockets_over_one_interval_and_ends_with_the_duration():
    ticks = _ticks(TrickleSpec(connections=4, byte_interval_s=2.0, duration_s=5.0))
    # socket i first at 100 + i * 2 / 4, then every 2 s; nothing at or after 105
    assert ticks[:4] == [(100.0, 0), (100.5, 1), (101.0, 2), (101.5, 3)]
    assert [t for t, i in ticks if i == 1] == [100.5, 102.5, 104.5]
    assert len(ticks) == 10 and max(t for t, _ in ticks) < 105.0
    assert [t for t, _ in ticks] == sorted(t for t, _ in ticks)


def test_the_plan_refuses_a_tick_out_of_order():
    plan = TricklePlan(TrickleSpec(connections=2, byte_interval_s=1.0, duration_s=3.0), 0.0)
    with pytest.raises(ValueError, match="not the next due"):
        plan.done(1, 0.5)


@pytest.mark.parametrize("kwargs", [dict(connections=0, byte_interval_s=1.0, duration_s=1.0),
                                    dict(connections=3, byte_interval_s=0.0, duration_s=1.0),
                                    dict(connections=3, byte_interval_s=1.0, duration_s=-1.0)])
def test_a_spec_without_sense_is_refused(kwargs):
    with pytest.raises(ValueError):
        TrickleSpec(**kwargs)


def test_endpoints():
    assert parse_endpoint("tcp/127.0.0.1:7447") == ("127.0.0.1", 7447)
    assert parse_endpoint("tcp/[::1]:7447") == ("::1", 7447)
    for bad in ("tls/127.0.0.1:7447", "udp/h:1", "tcp/nohost", "tcp/:1"):
        with pytest.raises(ValueError, match="not a tcp/HOST:PORT"):
            parse_endpoint(bad)


class _Listener:
    """A listener that, like a Zenoh one whose pending handshakes are all taken, closes every
    second connection at once and keeps the others, counting the bytes it reads on them."""

    def __init__(self):
        self.server = socket.create_server(("127.0.0.1", 0), backlog=256)
        self.server.settimeout(0.05)
        self.port = self.server.getsockname()[1]
        self.accepted = self.closed = 0
        self.kept: list[socket.socket] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self.server.accept()
            except TimeoutError:
                continue
            self.accepted += 1
            if self.accepted % 2 == 0:
                conn.close()
                self.closed += 1
            else:
                conn.setblocking(False)
                self.kept.append(conn)

    def bytes_read(self) -> int:
        total = 0
        for conn in self.kept:
            try:
                while data := conn.recv(4096):
                    total += len(data)
            except (BlockingIOError, ConnectionError):
                pass
        return total

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=2.0)
        for conn in self.kept:
            conn.close()
        self.server.close()


def test_the_trickle_holds_its_connections_and_reopens_what_the_listener_closed():
    listener = _Listener()
    try:
        spec = TrickleSpec(connections=10, byte_interval_s=0.2, duration_s=1.0)  # 5 ticks per socket
        counts = run_trickle("127.0.0.1", listener.port, spec)
        time.sleep(0.1)  # the last bytes reach the listener's buffers (loopback: at once)
        received = listener.bytes_read()
    finally:
        listener.close()
    assert counts.opens == 10 and counts.refused == 0
    # half of each round of connects is closed at once; each is found closed at the socket's next tick
    assert counts.closed_by_peer >= 5 and counts.reopens == counts.closed_by_peer
    assert listener.accepted == counts.opens + counts.reopens
    # one byte per tick: every byte sent on a connection the listener kept was read there
    assert 40 <= counts.bytes_sent <= 50
    assert 0 < received <= counts.bytes_sent


def test_connects_nobody_accepts_are_counted_as_refused():
    with socket.socket() as s:  # a port that was free a moment ago: nothing listens on it
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    counts = run_trickle("127.0.0.1", port, TrickleSpec(connections=3, byte_interval_s=0.1, duration_s=0.25))
    assert counts.opens == counts.bytes_sent == 0
    # ticks at 0, .1, .2 (socket 0), .033, .133, .233 (socket 1), .067, .167 (socket 2)
    assert counts.refused == 8 and counts.refused_by_errno == {"ECONNREFUSED": 8}


def test_a_stop_ends_the_trickle_early():
    stop = threading.Event()
    stop.set()
    t0 = time.monotonic()
    counts = run_trickle("127.0.0.1", 9, TrickleSpec(connections=5, byte_interval_s=10.0, duration_s=60.0), stop)
    assert time.monotonic() - t0 < 1.0 and counts == TrickleCounts()
