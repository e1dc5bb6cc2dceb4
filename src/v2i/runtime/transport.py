"""Zenoh session set-up shared by every service: explicit endpoints, no discovery.

Multicast scouting and gossip are off so that RSU and OBU never find each other
behind the link emulator's back; only the endpoints given here are used.

A site configuration file (Zenoh JSON5: TLS, mutual TLS, access control; see ``deploy/zenoh/``)
is merged into every session when ``$V2I_ZENOH_CONFIG`` names it (``--zenoh-config FILE`` on the
services sets it). The file is the base; the session's own endpoints replace the file's, and the
safety settings (no scouting or gossip, no shared memory, the codec's message size bound) are
applied over it. ``tls/HOST:PORT`` endpoints then work wherever ``tcp/`` ones do. In the file's
TLS paths ``${V2I_TLS_DIR}`` stands for ``$V2I_TLS_DIR`` (default ``/pki/tls``).

What a listen endpoint admits is bounded too (``session_bounds``): at most ``MAX_SESSIONS`` Zenoh
sessions with other nodes at once, ``ACCEPT_PENDING`` handshakes in progress, each given
``ACCEPT_TIMEOUT_MS`` to complete (a socket that connects and then trickles or says nothing is
closed after that), one link per session. Zenoh's defaults are 1000 sessions and 100 pending
handshakes of 10 s each. ``$V2I_ZENOH_BOUNDS=site`` leaves these four to the site file (or to
Zenoh's defaults where the file says nothing): for a deployment that needs more, or to measure
without them.
"""

from __future__ import annotations

import json
import os
import socket
from collections.abc import Sequence
from pathlib import Path

import yaml
import zenoh

from schemas.codec import MAX_MESSAGE_BYTES
from v2i.core.files import FileMissing, FileRefused, KiB, MiB, check_regular, read_text

# Services are Zenoh peers unless this variable says ``client``: behind a ``v2i router`` they
# must be clients, because a Zenoh 1.10 router forwards for its clients, never between peers.
SESSION_MODE_ENV = "V2I_ZENOH_MODE"
SESSION_MODES = ("peer", "client", "router")
CLIENT_CONNECT_TIMEOUT_MS = 10_000  # a client waits this long for its router, then gives up


CONFIG_FILE_ENV = "V2I_ZENOH_CONFIG"  # a Zenoh JSON5 file merged into every session
TLS_DIR_ENV = "V2I_TLS_DIR"
DEFAULT_TLS_DIR = "/pki/tls"
TLS_FILE_KEYS = ("root_ca_certificate", "listen_certificate", "listen_private_key", "connect_certificate",
                 "connect_private_key")
BOUNDS_ENV = "V2I_ZENOH_BOUNDS"  # v2i (default): the bounds below; site: the site file's / Zenoh's
BOUNDS_CHOICES = ("v2i", "site")
# A service's session reaches a handful of nodes: its link emulator(s) (one per RSU of the site at the
# OBU, the V2V relay), a watcher or monitor, a recorder, a replay, an operator's CLI; the largest bundled
# site (connected-intersection: 2 RSUs, 3 vehicles) gives an OBU 4-6 and the demo watcher 6. Zenoh counts
# the sessions a node opened with those it accepted. 32 leaves room for a larger site and bounds the
# memory a stranger's sessions can take (each may hold a reassembly buffer of the message size bound).
MAX_SESSIONS = 32
# A router serves every client of its side (RSUs, vehicles, consumers): Zenoh's default were too many
# to bound memory, 256 is more than any site here has nodes.
ROUTER_MAX_SESSIONS = 256
# Handshakes in progress at once: genuine peers connect one at a time (at start, after a restart).
ACCEPT_PENDING = 16
# A Zenoh handshake is 2 round trips (InitSyn/Ack, OpenSyn/Ack), TLS adds 1-2: well under 1 s on a
# site network or cellular backhaul (RTT <= 200 ms), 2 s allows 10 round trips. A socket that has not
# completed its handshake by then is closed, so a trickle holds a pending slot 2 s, not Zenoh's 10 s.
ACCEPT_TIMEOUT_MS = 2_000
MAX_LINKS = 1  # one link per session (no multilink): a peer cannot add links to its session
# A Zenoh configuration file, read here and parsed by Zenoh: deploy/router.json5 is ~3 kB.
ZENOH_CONFIG_LIMIT_BYTES = 1 * MiB
# A TLS certificate or key it names (PEM, opened by Zenoh after this check): ~1-2 kB, a chain a few.
TLS_FILE_LIMIT_BYTES = 64 * KiB


def session_mode() -> str:
    """``peer`` or ``client`` from ``$V2I_ZENOH_MODE`` (default peer); ValueError naming it otherwise."""
    mode = os.environ.get(SESSION_MODE_ENV, "").strip() or "peer"
    if mode not in SESSION_MODES[:2]:
        raise ValueError(f"{SESSION_MODE_ENV}={mode!r}: must be peer or client")
    return mode


def _zenoh_reason(exc: Exception) -> str:
    """Zenoh's error text without the Rust source location it ends with."""
    return str(exc).split(" at /", 1)[0].strip()


def load_config_file(path: str | Path) -> zenoh.Config:
    """The Zenoh configuration in ``path`` with ``${V2I_TLS_DIR}`` expanded in its TLS file paths.
    ValueError naming the file when it cannot be read or parsed, or names a TLS file that is missing."""
    path = Path(path)
    conf = read_config_file(path)
    tls_dir = os.environ.get(TLS_DIR_ENV, "").strip() or DEFAULT_TLS_DIR
    for key in TLS_FILE_KEYS:
        value = json.loads(conf.get_json(f"transport/link/tls/{key}"))
        if not isinstance(value, str):
            continue
        value = value.replace("${" + TLS_DIR_ENV + "}", tls_dir)
        try:
            check_regular(value, TLS_FILE_LIMIT_BYTES, "TLS file")
        except FileMissing:
            raise ValueError(f"Zenoh config {path}: transport/link/tls/{key} {value}: no such file "
                             f"(${TLS_DIR_ENV}={tls_dir}; v2i pki tls writes them)") from None
        except FileRefused as exc:
            raise ValueError(f"Zenoh config {path}: transport/link/tls/{key}: {exc}") from None
        conf.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
    return conf


def read_config_file(path: str | Path) -> zenoh.Config:
    """The Zenoh configuration in ``path`` as ``zenoh.Config.from_file`` reads it (``.json``,
    ``.json5`` or ``.yaml``), but from a regular file of at most ``ZENOH_CONFIG_LIMIT_BYTES`` read
    here; ValueError naming the file otherwise."""
    try:
        text = read_text(path, ZENOH_CONFIG_LIMIT_BYTES, "Zenoh config")
    except FileMissing:
        raise ValueError(f"Zenoh config {path}: no such file") from None
    except FileRefused as exc:
        raise ValueError(str(exc)) from None
    suffix = Path(path).suffix
    try:
        if suffix == ".yaml":
            return zenoh.Config.from_json5(json.dumps(yaml.safe_load(text)))
        if suffix in (".json", ".json5"):
            return zenoh.Config.from_json5(text)
    except (zenoh.ZError, yaml.YAMLError) as exc:
        raise ValueError(f"Zenoh config {path}: {_zenoh_reason(exc)}") from None
    raise ValueError(f"Zenoh config {path}: unsupported file type {suffix!r} (.json, .json5 and .yaml are supported)")


def use_config_file(path: str | Path) -> None:
    """Check ``path`` (:func:`load_config_file`) and make it this process's site configuration
    (``$V2I_ZENOH_CONFIG``, inherited by child processes): ``--zenoh-config FILE``."""
    load_config_file(path)
    os.environ[CONFIG_FILE_ENV] = str(Path(path).resolve())


def _base_config() -> tuple[zenoh.Config, str | None]:
    """The site file of ``$V2I_ZENOH_CONFIG`` (or an empty config) and the mode it sets, if any."""
    path = os.environ.get(CONFIG_FILE_ENV, "").strip()
    if not path:
        return zenoh.Config(), None
    try:
        conf = load_config_file(path)
    except ValueError as exc:
        raise ValueError(f"{CONFIG_FILE_ENV}: {exc}") from None
    return conf, json.loads(conf.get_json("mode"))


def bounds_source() -> str:
    """``v2i`` or ``site`` from ``$V2I_ZENOH_BOUNDS`` (default v2i); ValueError naming it otherwise."""
    choice = os.environ.get(BOUNDS_ENV, "").strip() or "v2i"
    if choice not in BOUNDS_CHOICES:
        raise ValueError(f"{BOUNDS_ENV}={choice!r}: must be v2i (the default) or site")
    return choice


def session_bounds(mode: str) -> dict[str, int]:
    """The Zenoh settings that bound what a session in ``mode`` admits (key -> value)."""
    return {"transport/unicast/max_sessions": ROUTER_MAX_SESSIONS if mode == "router" else MAX_SESSIONS,
            "transport/unicast/accept_pending": ACCEPT_PENDING,
            "transport/unicast/accept_timeout": ACCEPT_TIMEOUT_MS,
            "transport/unicast/max_links": MAX_LINKS}


def session_config(listen: Sequence[str] = (), connect: Sequence[str] = (), mode: str | None = None) -> zenoh.Config:
    """A config that listens on and connects to exactly these endpoints, over the site file of
    ``$V2I_ZENOH_CONFIG`` if set; ``mode`` one of ``SESSION_MODES``: the argument, else
    ``$V2I_ZENOH_MODE``, else the file's, else peer."""
    conf, file_mode = _base_config()
    if mode is None:
        mode = session_mode() if os.environ.get(SESSION_MODE_ENV, "").strip() or not file_mode else file_mode
    if mode not in SESSION_MODES:
        raise ValueError(f"Zenoh mode {mode!r}: must be one of {', '.join(SESSION_MODES)}")
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
    file_bound = json.loads(conf.get_json("transport/link/rx/max_message_size"))
    conf.insert_json5("transport/link/rx/max_message_size", str(min(file_bound or MAX_MESSAGE_BYTES, MAX_MESSAGE_BYTES)))
    if bounds_source() == "v2i":
        for key, value in session_bounds(mode).items():
            conf.insert_json5(key, str(value))
    return conf


def open_session(listen: Sequence[str] = (), connect: Sequence[str] = (), mode: str | None = None) -> zenoh.Session:
    """A Zenoh session on :func:`session_config`."""
    return zenoh.open(session_config(listen, connect, mode))


def free_tcp_endpoint(host: str = "127.0.0.1") -> str:
    """A ``tcp/host:port`` endpoint on a port that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return f"tcp/{host}:{s.getsockname()[1]}"
