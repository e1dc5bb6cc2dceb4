"""Zenoh session set-up shared by every service: explicit endpoints, no discovery.

Multicast scouting and gossip are off so that RSU and OBU never find each other
behind the link emulator's back; only the endpoints given here are used.
"""

from __future__ import annotations

import json
import os
import socket
from collections.abc import Sequence

import zenoh

from .codec import MAX_MESSAGE_BYTES

# Services are Zenoh peers unless this variable says ``client``: behind a ``v2i router`` they
# must be clients, because a Zenoh 1.10 router forwards for its clients, never between peers.
SESSION_MODE_ENV = "V2I_ZENOH_MODE"
SESSION_MODES = ("peer", "client", "router")
CLIENT_CONNECT_TIMEOUT_MS = 10_000  # a client waits this long for its router, then gives up


def session_mode() -> str:
    """``peer`` or ``client`` from ``$V2I_ZENOH_MODE`` (default peer); ValueError naming it otherwise."""
    mode = os.environ.get(SESSION_MODE_ENV, "").strip() or "peer"
    if mode not in SESSION_MODES[:2]:
        raise ValueError(f"{SESSION_MODE_ENV}={mode!r}: must be peer or client")
    return mode


def session_config(listen: Sequence[str] = (), connect: Sequence[str] = (), mode: str | None = None) -> zenoh.Config:
    """A config that listens on and connects to exactly these endpoints; ``mode`` one of
    ``SESSION_MODES``, default ``session_mode()``."""
    mode = session_mode() if mode is None else mode
    if mode not in SESSION_MODES:
        raise ValueError(f"Zenoh mode {mode!r}: must be one of {', '.join(SESSION_MODES)}")
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    # Keep retrying a peer that is down (e.g. a restarted link emulator) instead of giving up.
    conf.insert_json5("connect/exit_on_failure", "false")
    if mode == "client":  # Zenoh's default for a client: give up at once when its router is not up yet
        conf.insert_json5("connect/timeout_ms", str(CLIENT_CONNECT_TIMEOUT_MS))
    conf.insert_json5("listen/exit_on_failure", "true")
    # No shared-memory transport: V2X messages are small, and with it any local peer sending a
    # message over 3 kB makes the receiver map a 16 MB pool (measured: +20 MB RSS at once).
    conf.insert_json5("transport/shared_memory/enabled", "false")
    # Zenoh reassembles a fragmented message of up to 1 GB by default: a peer could make any
    # service allocate that much. Nothing on the wire is larger than the codec's limit.
    conf.insert_json5("transport/link/rx/max_message_size", str(MAX_MESSAGE_BYTES))
    return conf


def open_session(listen: Sequence[str] = (), connect: Sequence[str] = (), mode: str | None = None) -> zenoh.Session:
    return zenoh.open(session_config(listen, connect, mode))


def free_tcp_endpoint(host: str = "127.0.0.1") -> str:
    """A ``tcp/host:port`` endpoint on a port that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return f"tcp/{host}:{s.getsockname()[1]}"
