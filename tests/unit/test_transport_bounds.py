"""What a service's listen endpoint admits (v2i.runtime.transport): sessions, pending handshakes and
their time, over any site file; ``$V2I_ZENOH_BOUNDS=site`` hands them back to the file. Live checks
against a Zenoh listener on a free loopback port; and where Zenoh drops an oversized payload."""

from __future__ import annotations

import json
import socket
import threading
import time
from pathlib import Path

import pytest

from schemas.codec import MAX_MESSAGE_BYTES
from v2i.runtime import transport
from v2i.runtime.transport import (ACCEPT_PENDING, ACCEPT_TIMEOUT_MS, BOUNDS_ENV, CONFIG_FILE_ENV, MAX_SESSIONS,
                                   ROUTER_MAX_SESSIONS, free_tcp_endpoint, open_session, session_config)
from v2i.adversary.trickle import parse_endpoint

KEY = "v2x/rsu/bounds/objects"
ZENOH_DEFAULTS = {"max_sessions": 1000, "accept_pending": 100, "accept_timeout": 10_000}


def _unicast(conf) -> dict:
    return json.loads(conf.get_json("transport/unicast"))


@pytest.fixture(autouse=True)
def _no_site(monkeypatch):
    for name in (CONFIG_FILE_ENV, BOUNDS_ENV, "V2I_ZENOH_MODE"):
        monkeypatch.delenv(name, raising=False)


def _site(tmp_path: Path, monkeypatch, **unicast) -> None:
    site = tmp_path / "site.json5"
    site.write_text(json.dumps({"transport": {"unicast": unicast}}))
    monkeypatch.setenv(CONFIG_FILE_ENV, str(site))


def test_the_bounds_apply_to_every_mode_over_the_site_file(tmp_path, monkeypatch):
    _site(tmp_path, monkeypatch, max_sessions=5000, accept_pending=900, accept_timeout=60_000, max_links=4)
    for mode, sessions in (("peer", MAX_SESSIONS), ("client", MAX_SESSIONS), ("router", ROUTER_MAX_SESSIONS)):
        unicast = _unicast(session_config(listen=["tcp/127.0.0.1:7447"], mode=mode))
        assert (unicast["max_sessions"], unicast["accept_pending"], unicast["accept_timeout"], unicast["max_links"]) \
            == (sessions, ACCEPT_PENDING, ACCEPT_TIMEOUT_MS, 1), mode
    # tighter than Zenoh's own
    assert MAX_SESSIONS < ROUTER_MAX_SESSIONS < ZENOH_DEFAULTS["max_sessions"]
    assert ACCEPT_PENDING < ZENOH_DEFAULTS["accept_pending"] and ACCEPT_TIMEOUT_MS < ZENOH_DEFAULTS["accept_timeout"]


def test_bounds_site_leaves_them_to_the_file_or_to_zenoh(tmp_path, monkeypatch):
    monkeypatch.setenv(BOUNDS_ENV, "site")
    unicast = _unicast(session_config())
    assert {k: unicast[k] for k in ZENOH_DEFAULTS} == ZENOH_DEFAULTS
    _site(tmp_path, monkeypatch, max_sessions=200, accept_timeout=5_000)
    unicast = _unicast(session_config())
    assert (unicast["max_sessions"], unicast["accept_timeout"], unicast["accept_pending"]) == (200, 5_000, 100)
    # the other safety settings stay: the message size bound
    assert json.loads(session_config().get_json("transport/link/rx/max_message_size")) == MAX_MESSAGE_BYTES


def test_a_bad_bounds_choice_is_named(monkeypatch):
    monkeypatch.setenv(BOUNDS_ENV, "none")
    with pytest.raises(ValueError, match="V2I_ZENOH_BOUNDS='none': must be v2i"):
        session_config()


def _closed_within(sock: socket.socket, seconds: float) -> float | None:
    """Seconds until the listener closed ``sock`` (EOF or reset), None if still open after ``seconds``."""
    t0 = time.monotonic()
    sock.settimeout(seconds)
    try:
        while sock.recv(4096):
            pass
    except TimeoutError:
        return None
    except ConnectionError:
        pass
    return time.monotonic() - t0


def test_a_silent_connection_is_closed_after_the_accept_timeout_and_one_beyond_the_pending_at_once():
    endpoint = free_tcp_endpoint()
    host, port = parse_endpoint(endpoint)
    listener = open_session(listen=[endpoint])
    silent: list[socket.socket] = []
    try:
        silent = [socket.create_connection((host, port), timeout=2.0) for _ in range(ACCEPT_PENDING)]
        time.sleep(0.3)  # the listener has taken all of them into its handshakes (loopback: at once)
        with socket.create_connection((host, port), timeout=2.0) as one_more:
            beyond = _closed_within(one_more, 1.0)
        assert beyond is not None and beyond < 1.0  # no pending slot free: closed at once
        # a handshake that says nothing ends at the accept timeout (2 s), not Zenoh's 10 s
        waited = _closed_within(silent[0], ACCEPT_TIMEOUT_MS / 1000 + 2.0)
        assert waited is not None and waited < ACCEPT_TIMEOUT_MS / 1000 + 1.0
    finally:
        for sock in silent:
            sock.close()
        listener.close()


def _wait(predicate, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def test_sessions_beyond_the_bound_are_refused(monkeypatch):
    monkeypatch.setattr(transport, "MAX_SESSIONS", 2)
    endpoint = free_tcp_endpoint()
    listener = open_session(listen=[endpoint])
    got: list[bytes] = []
    sub = listener.declare_subscriber(KEY, lambda s: got.append(s.payload.to_bytes()))
    peers = []
    try:
        peers = [open_session(connect=[endpoint]) for _ in range(3)]
        assert _wait(lambda: len(list(listener.info.peers_zid())) == 2, 10.0)
        time.sleep(1.0)  # the third keeps retrying: still refused
        assert len(list(listener.info.peers_zid())) == 2
        admitted = [p for p in peers if list(p.info.peers_zid())]
        refused = [p for p in peers if not list(p.info.peers_zid())]
        assert len(admitted) == 2 and len(refused) == 1
        refused[0].put(KEY, b"stranger")
        admitted[0].put(KEY, b"admitted")
        assert _wait(lambda: b"admitted" in got, 5.0) and b"stranger" not in got
    finally:
        sub.undeclare()
        for peer in peers:
            peer.close()
        listener.close()


def test_payloads_over_the_message_bound_vanish_in_zenoh_and_the_session_goes_on():
    """Zenoh's reassembly limit is the codec's bound: measured, a payload of up to MAX - 6 bytes
    arrives (6 bytes of Zenoh header on a declared key), 1 MiB and more do not, uncounted by v2i."""
    endpoint = free_tcp_endpoint()
    listener = open_session(listen=[endpoint])
    sizes: list[int] = []
    arrived = threading.Event()

    def on_sample(sample) -> None:
        sizes.append(len(sample.payload.to_bytes()))
        arrived.set()

    sub = listener.declare_subscriber(KEY, on_sample)
    sender = open_session(connect=[endpoint])
    try:
        assert _wait(lambda: list(sender.info.peers_zid()), 10.0)
        outcome = {}
        for size in (1_000_000, MAX_MESSAGE_BYTES - 64, MAX_MESSAGE_BYTES, 2_000_000, 1000):
            arrived.clear()
            sender.put(KEY, bytes(size))
            outcome[size] = arrived.wait(2.0)
        assert outcome == {1_000_000: True, MAX_MESSAGE_BYTES - 64: True, MAX_MESSAGE_BYTES: False,
                           2_000_000: False, 1000: True}
        assert sizes == [1_000_000, MAX_MESSAGE_BYTES - 64, 1000]
    finally:
        sub.undeclare()
        sender.close()
        listener.close()
