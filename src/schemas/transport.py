"""Zenoh session set-up shared by every service: explicit endpoints, no discovery.

Multicast scouting and gossip are off so that RSU and OBU never find each other
behind the link emulator's back; only the endpoints given here are used.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Sequence

import zenoh

from .codec import MAX_MESSAGE_BYTES


def session_config(listen: Sequence[str] = (), connect: Sequence[str] = ()) -> zenoh.Config:
    """A peer-mode config that listens on and connects to exactly these endpoints."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    # Keep retrying a peer that is down (e.g. a restarted link emulator) instead of giving up.
    conf.insert_json5("connect/exit_on_failure", "false")
    conf.insert_json5("listen/exit_on_failure", "true")
    # No shared-memory transport: V2X messages are small, and with it any local peer sending a
    # message over 3 kB makes the receiver map a 16 MB pool (measured: +20 MB RSS at once).
    conf.insert_json5("transport/shared_memory/enabled", "false")
    # Zenoh reassembles a fragmented message of up to 1 GB by default: a peer could make any
    # service allocate that much. Nothing on the wire is larger than the codec's limit.
    conf.insert_json5("transport/link/rx/max_message_size", str(MAX_MESSAGE_BYTES))
    return conf


def open_session(listen: Sequence[str] = (), connect: Sequence[str] = ()) -> zenoh.Session:
    return zenoh.open(session_config(listen, connect))


def free_tcp_endpoint(host: str = "127.0.0.1") -> str:
    """A ``tcp/host:port`` endpoint on a port that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return f"tcp/{host}:{s.getsockname()[1]}"
