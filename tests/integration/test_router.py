"""``v2i router`` as a process on loopback: clients meet through it, routers chain, it stops cleanly.

Every wait has a deadline; a message that does not arrive fails the test instead of hanging it.
"""

from __future__ import annotations

import json
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import pytest
import zenoh

from v2i.orchestration.children import READY_TIMEOUT_S, Child, wait_ready
from v2i.runtime.transport import (
    CLIENT_CONNECT_TIMEOUT_MS,
    SESSION_MODE_ENV,
    free_tcp_endpoint,
    open_session,
    session_config,
    session_mode,
)

pytestmark = [pytest.mark.integration, pytest.mark.timeout(90 + 3 * READY_TIMEOUT_S)]  # three routers at most

ROUTER_CONFIG = Path(__file__).resolve().parents[2] / "deploy" / "router.json5"
DELIVERY_S = 5.0  # a message through a ready router, including the clients' interest exchange
# how long v2i's client waits for its router before giving up (s); a router process was ready 1.1-1.2 s after
# its start with two busy loops on the 2 cores (load ~12)
CLIENT_WAIT_S = CLIENT_CONNECT_TIMEOUT_MS / 1000
KEY = "v2x/test/router"


@contextmanager
def router(*args: str) -> Iterator[Child]:
    """A ``v2i router`` process, ready; stopped with SIGTERM afterwards."""
    child = Child("router", [sys.executable, "-m", "v2i", "router", *args])
    try:
        wait_ready([child])
        yield child
    finally:
        child.stop()


@contextmanager
def client(endpoint: str, mode: str = "client") -> Iterator[zenoh.Session]:
    session = open_session(connect=[endpoint], mode=mode)
    try:
        yield session
    finally:
        session.close()


def _delivered(sender: zenoh.Session, receiver: zenoh.Session, timeout_s: float) -> list[bytes]:
    """Payloads the receiver got while the sender put one message every 100 ms, until the first
    arrived or ``timeout_s`` passed (the subscription needs a moment to reach the router)."""
    inbox: queue.Queue[bytes] = queue.Queue()
    subscriber = receiver.declare_subscriber(KEY, lambda s: inbox.put(s.payload.to_bytes()))
    try:
        deadline = time.monotonic() + timeout_s
        n = 0
        while time.monotonic() < deadline:
            sender.put(KEY, f"hello {n}".encode())
            n += 1
            try:
                return [inbox.get(timeout=0.1)]
            except queue.Empty:
                continue
        return []
    finally:
        subscriber.undeclare()


def test_two_clients_exchange_messages_and_queries_through_the_router() -> None:
    ep = free_tcp_endpoint()
    with router("--listen", ep), client(ep) as rsu, client(ep) as obu:
        got = _delivered(rsu, obu, DELIVERY_S)
        assert got and got[0].startswith(b"hello"), "no message crossed the router"
        # The time service is a queryable: a query from one client reaches the other's and back.
        queryable = rsu.declare_queryable("v2x/test/time", lambda q: q.reply(q.key_expr, b"t2t3"))
        try:
            replies: list[bytes] = []
            deadline = time.monotonic() + DELIVERY_S
            while not replies and time.monotonic() < deadline:
                replies = [r.ok.payload.to_bytes() for r in obu.get("v2x/test/time", timeout=1.0) if r.ok]
            assert replies == [b"t2t3"]
        finally:
            queryable.undeclare()


def test_peers_are_not_routed_so_services_behind_a_router_are_clients() -> None:
    """Zenoh 1.10 routers do not forward between two peers (no failover brokering): the reason
    the services attach to a router with V2I_ZENOH_MODE=client. Should Zenoh bring brokering
    back, this fails and peers could stay peers."""
    ep = free_tcp_endpoint()
    with router("--listen", ep), client(ep, mode="peer") as a, client(ep, mode="peer") as b:
        assert _delivered(a, b, 2.0) == []


def test_a_client_started_before_its_router_waits_for_it() -> None:
    """Zenoh's default client gives up at once; v2i's waits CLIENT_CONNECT_TIMEOUT_MS (10 s)."""
    ep = free_tcp_endpoint()
    opened: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: opened.put(_open_or_error(ep)), daemon=True).start()
    time.sleep(1.0)
    assert opened.empty(), "the client gave up (or connected) before any router was up"
    with router("--listen", ep):
        early = opened.get(timeout=CLIENT_WAIT_S)  # it connected, or gave up, within its own wait
        assert isinstance(early, zenoh.Session), f"the early client failed: {early}"
        try:
            with client(ep) as late:
                assert _delivered(late, early, DELIVERY_S)
        finally:
            early.close()


def _open_or_error(ep: str) -> zenoh.Session | Exception:
    try:
        return open_session(connect=[ep], mode="client")
    except zenoh.ZError as exc:
        return exc


def test_routers_chain_and_unconnected_routers_stay_apart() -> None:
    ep1, ep2, ep3 = free_tcp_endpoint(), free_tcp_endpoint(), free_tcp_endpoint()
    with ExitStack() as stack:
        stack.enter_context(router("--listen", ep1))
        stack.enter_context(router("--listen", ep2, "--connect", ep1))  # router-to-router
        stack.enter_context(router("--listen", ep3))  # another side: connected to nobody
        near, far, apart = (stack.enter_context(client(ep)) for ep in (ep1, ep2, ep3))
        assert _delivered(far, near, DELIVERY_S), "no message crossed the two connected routers"
        assert _delivered(near, apart, 2.0) == [], "a message reached a router nobody connected to"


def test_router_config_file_routes_and_its_endpoints_are_replaced() -> None:
    ep = free_tcp_endpoint()
    with router("--config", str(ROUTER_CONFIG), "--listen", ep) as child, client(ep) as a, client(ep) as b:
        assert _delivered(a, b, DELIVERY_S)
    assert child.proc.returncode == 0


def test_router_stops_on_sigterm_and_after_its_duration_and_logs_endpoints() -> None:
    ep = free_tcp_endpoint()
    proc = subprocess.Popen([sys.executable, "-m", "v2i", "router", "--listen", ep, "--duration", "60"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: queue.Queue[str] = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(line) for line in proc.stderr], daemon=True)
    reader.start()
    try:
        ready = json.loads(proc.stdout.readline())  # blocks until ready; the test's timeout bounds it
        assert ready["event"] == "ready" and ready["listen"] == [ep] and ready["connect"] == []
        err, deadline = [], time.monotonic() + DELIVERY_S
        with client(ep):  # until its transport event is in the router's log
            while not any("connected" in line for line in err) and (left_s := deadline - time.monotonic()) > 0:
                try:
                    err.append(lines.get(timeout=left_s))
                except queue.Empty:
                    break
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10.0)
        assert proc.returncode == 0 and time.monotonic() - t0 < 5.0
        reader.join(5.0)
        err = "".join(err) + "".join(lines.get() for _ in range(lines.qsize()))
        assert f"listening on {ep}" in err and "client" in err and "connected" in err and "stopped" in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "v2i", "router", "--listen", free_tcp_endpoint(), "--duration", "1"],
                          check=False, capture_output=True, text=True, timeout=30.0)
    assert done.returncode == 0 and json.loads(done.stdout.splitlines()[0])["event"] == "ready"
    assert time.monotonic() - t0 < 20.0


@pytest.mark.parametrize(("args", "message"), [
    (["--duration", "0"], "--duration"),
    (["--connect", "tcp/127.0.0.1:1", "--config", "/nonexistent.json5"], "/nonexistent.json5"),
])
def test_router_refuses_bad_options_in_one_line(args: list[str], message: str) -> None:
    done = subprocess.run([sys.executable, "-m", "v2i", "router", *args], check=False, capture_output=True, text=True, timeout=30.0)
    assert done.returncode == 2 and message in done.stderr and len(done.stderr.strip().splitlines()) == 1


def test_router_refuses_a_config_file_of_another_mode(tmp_path: Path) -> None:
    peer = tmp_path / "peer.json5"
    peer.write_text('{ mode: "peer" }')
    done = subprocess.run([sys.executable, "-m", "v2i", "router", "--config", str(peer)],
                          check=False, capture_output=True, text=True, timeout=30.0)
    assert done.returncode == 2 and "mode is 'peer'" in done.stderr


def test_session_mode_comes_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(SESSION_MODE_ENV, raising=False)
    assert session_mode() == "peer"
    monkeypatch.setenv(SESSION_MODE_ENV, "client")
    assert session_mode() == "client"
    assert json.loads(session_config(connect=["tcp/127.0.0.1:1"]).get_json("mode")) == "client"
    monkeypatch.setenv(SESSION_MODE_ENV, "router")  # only v2i router runs a router
    with pytest.raises(ValueError, match=SESSION_MODE_ENV):
        session_mode()
