"""A slow trickle of TCP connections: N raw sockets to a listen endpoint, one byte every I seconds
each, reopened when the listener closed them, for D seconds (issue 32, "hostile air").

No Zenoh here: the sockets never complete a Zenoh handshake, they only hold the listener's
accept slots (Zenoh 1.10: ``transport/unicast/accept_pending`` handshakes at once, each given
``accept_timeout`` to finish; a link beyond the pending bound is closed at once). Each socket
acts on its own tick only: it connects (a refused or timed-out connect counts, and is tried again
at its next tick), sends one byte, and on finding its connection closed by the listener opens a
new one at once (a reopen). The ticks of the N sockets are spread evenly over one interval, so
the listener sees N / I bytes and connects per second, not bursts.

The byte is 0xff: a Zenoh TCP link reads a 2-byte little-endian frame length first, and 0xffff
is a frame as long as a link allows, so the handshake stays incomplete for as long as the
trickle lasts (a 0 length would be refused as an empty frame at once).

``TricklePlan`` (pure) says when each socket acts; ``run_trickle`` is the thin socket loop.
"""

from __future__ import annotations

import errno
import heapq
import socket
import threading
import time
from dataclasses import asdict, dataclass, field

TRICKLE_BYTE = b"\xff"
CONNECT_TIMEOUT_S = 0.5  # a connect the listener's backlog leaves hanging counts as refused after this
MAX_CONNECTIONS = 4096  # sockets one trickle may hold (below a default 'ulimit -n' of 1024: say so when it fails)


@dataclass(frozen=True)
class TrickleSpec:
    """N connections (``connections``), one byte each every ``byte_interval_s``, for ``duration_s``."""

    connections: int
    byte_interval_s: float
    duration_s: float

    def __post_init__(self) -> None:
        if not 1 <= self.connections <= MAX_CONNECTIONS:
            raise ValueError(f"trickle connections must be 1..{MAX_CONNECTIONS}, not {self.connections}")
        if not self.byte_interval_s > 0 or not self.duration_s > 0:
            raise ValueError("trickle byte interval and duration must be > 0 s")


@dataclass
class TrickleCounts:
    """What the trickle did: sockets connected first (``opens``) and again after the listener closed
    them (``reopens``), connects refused or timed out (``refused``), closes seen (``closed_by_peer``),
    bytes sent and the ones whose send failed (``send_errors``)."""

    opens: int = 0
    reopens: int = 0
    refused: int = 0
    closed_by_peer: int = 0
    bytes_sent: int = 0
    send_errors: int = 0
    refused_by_errno: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return asdict(self)


class TricklePlan:
    """When each of the N sockets acts: socket ``i`` first at ``start_s + i * I / N``, then every
    ``I`` seconds (I = ``byte_interval_s``), until ``start_s + duration_s``. Pure: times are
    arguments."""

    def __init__(self, spec: TrickleSpec, start_s: float):
        self.spec, self.start_s, self.end_s = spec, start_s, start_s + spec.duration_s
        self._ticks = [0] * spec.connections  # ticks each socket has had
        self._due: list[tuple[float, int]] = [(self._time(i), i) for i in range(spec.connections)]
        heapq.heapify(self._due)

    def _time(self, index: int) -> float:
        """Socket ``index``'s next tick: t = start + (index / N + k) * I, k its ticks so far."""
        spec = self.spec
        return self.start_s + (index / spec.connections + self._ticks[index]) * spec.byte_interval_s

    def next_due(self) -> tuple[float, int] | None:
        """(time, socket index) of the next action, None once that time is past the end."""
        due_s, index = self._due[0]
        return None if due_s >= self.end_s else (due_s, index)

    def done(self, index: int, due_s: float) -> None:
        """Socket ``index`` acted for its tick ``due_s``: its next tick is one interval later."""
        popped = heapq.heappop(self._due)
        if popped != (due_s, index):
            raise ValueError(f"socket {index} at {due_s} is not the next due ({popped})")
        self._ticks[index] += 1
        heapq.heappush(self._due, (self._time(index), index))


def _closed_by_peer(sock: socket.socket) -> bool:
    """Whether the listener closed (or reset) this non-blocking connection; what it sent is discarded."""
    try:
        while True:
            data = sock.recv(4096)
            if not data:
                return True
    except BlockingIOError:
        return False
    except OSError:
        return True


class _Sockets:
    """The thin I/O shell: one optional socket per index, opened, fed and closed on demand."""

    def __init__(self, host: str, port: int, counts: TrickleCounts):
        self.host, self.port, self.counts = host, port, counts
        self.open: dict[int, socket.socket] = {}
        self.ever_opened: set[int] = set()

    def act(self, index: int) -> None:
        """Socket ``index``'s tick: reopen it if the listener closed it, connect if it has none, send one byte."""
        sock = self.open.get(index)
        if sock is not None and _closed_by_peer(sock):
            self.counts.closed_by_peer += 1
            self.close(index)
            sock = None
        if sock is None:
            sock = self._connect(index)
            if sock is None:
                return
        try:
            sock.send(TRICKLE_BYTE)
            self.counts.bytes_sent += 1
        except OSError:
            self.counts.send_errors += 1
            self.close(index)

    def _connect(self, index: int) -> socket.socket | None:
        try:
            sock = socket.create_connection((self.host, self.port), timeout=CONNECT_TIMEOUT_S)
        except OSError as exc:
            self.counts.refused += 1
            name = errno.errorcode.get(exc.errno, "timeout") if exc.errno else "timeout"
            self.counts.refused_by_errno[name] = self.counts.refused_by_errno.get(name, 0) + 1
            if exc.errno == errno.EMFILE:
                raise OSError(exc.errno, "trickle: out of file descriptors (raise 'ulimit -n' or use fewer "
                                         "connections)") from None
            return None
        sock.setblocking(False)
        if index in self.ever_opened:
            self.counts.reopens += 1
        else:
            self.counts.opens += 1
            self.ever_opened.add(index)
        self.open[index] = sock
        return sock

    def close(self, index: int) -> None:
        sock = self.open.pop(index, None)
        if sock is not None:
            sock.close()

    def close_all(self) -> None:
        for index in list(self.open):
            self.close(index)


def run_trickle(host: str, port: int, spec: TrickleSpec, stop: threading.Event | None = None) -> TrickleCounts:
    """Trickle ``spec`` against ``host:port`` until its duration ends or ``stop`` is set; every
    socket is closed on return. The counts, also when ``stop`` ended it early."""
    stop = stop or threading.Event()
    counts = TrickleCounts()
    sockets = _Sockets(host, port, counts)
    plan = TricklePlan(spec, time.monotonic())
    try:
        while (due := plan.next_due()) is not None:
            due_s, index = due
            if stop.wait(max(due_s - time.monotonic(), 0.0)):
                break
            sockets.act(index)
            plan.done(index, due_s)
    finally:
        sockets.close_all()
    return counts


def parse_endpoint(endpoint: str) -> tuple[str, int]:
    """(host, port) of a ``tcp/HOST:PORT`` endpoint; ValueError for any other kind (a trickle is raw TCP)."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if proto != "tcp" or not host or not port.isdigit():
        raise ValueError(f"trickle: {endpoint!r} is not a tcp/HOST:PORT endpoint")
    return host.strip("[]"), int(port)
