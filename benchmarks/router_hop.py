"""Message latency through ``v2i router`` against a direct peer connection, on loopback.

This process holds both ends: a sender session puts numbered messages at a fixed rate, each
carrying its send time (``time.perf_counter_ns``, this process's monotonic clock), and a
receiver session's subscriber stamps their arrival, so that one clock measures the one-way
latency (receive - send) without any synchronisation error. Topologies, all TCP on 127.0.0.1,
scouting and gossip off:

- ``direct``: two peers, the receiver listening, the sender connected to it (v2i's default);
- ``router``: two clients of one ``v2i router`` process (one extra process and TCP hop);
- ``2-routers``: the sender a client of one router, the receiver of another, the routers
  connected (router-to-router).

The first messages of each run only wait for the route (until one arrives) and are not counted.

    python benchmarks/router_hop.py [--count 2000] [--rate-hz 200] [--sizes 256,4096] [--json]
"""

from __future__ import annotations

import argparse
import json
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

import numpy as np
import zenoh

from v2i.runtime.transport import free_tcp_endpoint, open_session

KEY = "v2x/bench/router_hop"
HEADER = struct.Struct("<qq")  # (sequence number, send time in perf_counter ns)
ROUTE_WAIT_S = 10.0  # a route not up after this long is a failure, not a slow result
READY_S = 20.0


@contextmanager
def router_process(listen: str, connect: str | None = None) -> Iterator[None]:
    """A ``v2i router`` subprocess, ready (its JSON line read); terminated afterwards."""
    argv = [sys.executable, "-m", "v2i", "router", "--listen", listen, *(["--connect", connect] if connect else [])]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        timer = threading.Timer(READY_S, proc.kill)  # a router that never gets ready ends the wait
        timer.start()
        line = proc.stdout.readline()
        timer.cancel()
        if json.loads(line or "{}").get("event") != "ready":
            raise RuntimeError(f"v2i router on {listen} did not get ready (exit code {proc.poll()})")
        yield
    finally:
        proc.terminate()
        proc.wait(10)


@contextmanager
def sessions(topology: str) -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """(sender, receiver) for ``topology``; everything closed afterwards."""
    with ExitStack() as stack:
        if topology == "direct":
            ep = free_tcp_endpoint()
            receiver = stack.enter_context(open_session(listen=[ep], mode="peer"))
            sender = stack.enter_context(open_session(connect=[ep], mode="peer"))
        elif topology == "router":
            ep = free_tcp_endpoint()
            stack.enter_context(router_process(ep))
            receiver = stack.enter_context(open_session(connect=[ep], mode="client"))
            sender = stack.enter_context(open_session(connect=[ep], mode="client"))
        elif topology == "2-routers":
            ep1, ep2 = free_tcp_endpoint(), free_tcp_endpoint()
            stack.enter_context(router_process(ep1))
            stack.enter_context(router_process(ep2, connect=ep1))
            receiver = stack.enter_context(open_session(connect=[ep2], mode="client"))
            sender = stack.enter_context(open_session(connect=[ep1], mode="client"))
        else:
            raise ValueError(f"unknown topology {topology!r}")
        yield sender, receiver


def measure(topology: str, size_bytes: int, count: int, rate_hz: float) -> np.ndarray:
    """One-way latencies (us) of ``count`` messages of ``size_bytes``; shape (received,)."""
    received: dict[int, int] = {}  # sequence -> receive perf_counter ns (negative sequences: warm-up)
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        now_ns = time.perf_counter_ns()
        seq, sent_ns = HEADER.unpack_from(sample.payload.to_bytes())
        with lock:
            received[seq] = now_ns - sent_ns

    padding = bytes(max(0, size_bytes - HEADER.size))
    with sessions(topology) as (sender, receiver):
        subscriber = receiver.declare_subscriber(KEY, on_sample)
        publisher = sender.declare_publisher(KEY)
        try:
            _wait_for_route(publisher, padding, received, lock)
            period_ns = round(1e9 / rate_hz)
            next_ns = time.perf_counter_ns()
            for seq in range(count):
                next_ns += period_ns
                while (wait_ns := next_ns - time.perf_counter_ns()) > 0:
                    time.sleep(wait_ns * 1e-9)
                publisher.put(HEADER.pack(seq, time.perf_counter_ns()) + padding)
            time.sleep(0.5)  # stragglers
        finally:
            publisher.undeclare()
            subscriber.undeclare()
    with lock:
        return np.array([v for k, v in received.items() if k >= 0], dtype=np.float64) / 1e3


def _wait_for_route(publisher, padding: bytes, received: dict[int, int], lock: threading.Lock) -> None:
    """Put warm-up messages (negative sequence numbers) every 10 ms until one arrives."""
    deadline = time.monotonic() + ROUTE_WAIT_S
    seq = -1
    while time.monotonic() < deadline:
        publisher.put(HEADER.pack(seq, time.perf_counter_ns()) + padding)
        seq -= 1
        time.sleep(0.01)
        with lock:
            if received:
                return
    raise RuntimeError(f"no route within {ROUTE_WAIT_S:g} s")


def summary(latencies_us: np.ndarray, count: int) -> dict:
    """p50 / p99 / max in us and the share of messages received."""
    if not latencies_us.size:
        return {"received": 0, "sent": count, "p50_us": None, "p99_us": None, "max_us": None}
    p50, p99 = np.percentile(latencies_us, [50, 99])
    return {"received": int(latencies_us.size), "sent": count, "p50_us": round(float(p50), 1),
            "p99_us": round(float(p99), 1), "max_us": round(float(latencies_us.max()), 1)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=2000, help="messages per run (default %(default)s)")
    parser.add_argument("--rate-hz", type=float, default=200.0, help="messages per second (default %(default)s)")
    parser.add_argument("--sizes", default="256,4096", help="payload sizes in bytes, comma-separated (default %(default)s)")
    parser.add_argument("--topologies", default="direct,router,2-routers",
                        help="comma-separated, of direct, router, 2-routers (default %(default)s)")
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    args = parser.parse_args()
    results = []
    for size in (int(s) for s in args.sizes.split(",")):
        for topology in args.topologies.split(","):
            row = {"topology": topology, "size_bytes": size,
                   **summary(measure(topology, size, args.count, args.rate_hz), args.count)}
            results.append(row)
            if not args.json:
                print(f"{topology:>9} {size:>6} B: p50 {row['p50_us']} us  p99 {row['p99_us']} us  "
                      f"max {row['max_us']} us  ({row['received']}/{row['sent']} received)", flush=True)
    if args.json:
        print(json.dumps({"count": args.count, "rate_hz": args.rate_hz, "results": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
