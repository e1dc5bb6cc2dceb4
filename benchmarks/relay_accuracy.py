"""Live link relay timing accuracy: how close to its drawn due time is each message relayed?

A real ``LinkRelay`` runs in its own process (as ``v2i link`` does, so that it has a GIL of
its own) between two Zenoh sessions of this process on free loopback ports, scouting off.
This process puts numbered messages on the RSU side at a fixed rate and timestamps them on
arrival at the vehicle side. Two errors are reported, in ms:

- lateness: fired - due inside the relay (scheduler wake-up and queueing only);
- end-to-end: vehicle receive - (RSU send + drawn delay), i.e. lateness plus both Zenoh
  hops and the subscriber callback; this is what the OBU actually sees.

The drawn delay of each message comes from the relay's delivery observer (due - relay receive).
Target: p99 <= 1 ms at 1000 msg/s.

    python benchmarks/relay_accuracy.py [--rate-hz 1000] [--duration-s 10] [--profile NAME|PATH] [--json]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import struct
import sys
import tempfile
import threading
import time
from array import array
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Self

import numpy as np

from link_emulator.config import LinkConfig
from link_emulator.relay import Delivery, LinkRelay
from schemas.keys import rsu_objects
from v2i.runtime.transport import free_tcp_endpoint, open_session
from v2i.sim.clock import SystemClock

NS_PER_MS = 1_000_000
KEY = rsu_objects("bench")
HEADER = struct.Struct("<qq")  # seq, RSU send time (ns); probes have seq < 0
TARGET_P99_MS = 1.0
# Base 40 ms plus lognormal jitter (median 10 ms, heavy tail): at 1000 msg/s some 50 messages are
# in flight at once and overtake each other, so the relay's heap is exercised, not just a FIFO.
DEFAULT_PROFILE = """\
name: bench-jitter
uplink: {delay_ms: 20.0}
downlink:
  delay_ms: 40.0
  jitter: {distribution: lognormal, median_ms: 10.0, sigma: 0.6}
"""


# ---- the relay process ------------------------------------------------------------------


def _relay_process(config_json: str, stop_mp: mp.synchronize.Event, results: Connection) -> None:
    """Run a LinkRelay until ``stop_mp``; send back seq, relay receive, due and fired ns per message."""
    columns = tuple(array("q") for _ in range(4))

    def observe(delivery: Delivery) -> None:
        seq = HEADER.unpack_from(delivery.payload)[0]
        for column, value in zip(columns, (seq, delivery.receive_ns, delivery.due_ns, delivery.fired_ns), strict=True):
            column.append(value)

    relay = LinkRelay(LinkConfig.model_validate_json(config_json), SystemClock(), observer=observe)
    stop = threading.Event()
    threading.Thread(target=lambda: (stop_mp.wait(), stop.set()), daemon=True).start()
    relay.run(stop)
    results.send(([c.tobytes() for c in columns], relay.stats_snapshot(time.time_ns())))
    results.close()


# ---- the two ends ---------------------------------------------------------------------


@dataclass
class Ends:
    """RSU and vehicle sessions of this process; what the vehicle received."""

    rsu_endpoint: str = field(default_factory=free_tcp_endpoint)
    vehicle_endpoint: str = field(default_factory=free_tcp_endpoint)
    received: list[tuple[int, bytes]] = field(default_factory=list)  # (receive ns, payload)

    def __enter__(self) -> Self:
        self.rsu = open_session(listen=[self.rsu_endpoint])
        self.vehicle = open_session(listen=[self.vehicle_endpoint])
        self.publisher = self.rsu.declare_publisher(KEY)
        # Stamp first, parse later: the callback must be as short as possible.
        self.subscriber = self.vehicle.declare_subscriber(
            KEY, lambda s: self.received.append((time.time_ns(), s.payload.to_bytes()))
        )
        return self

    def __exit__(self, *exc: object) -> None:
        self.subscriber.undeclare()
        self.publisher.undeclare()
        self.vehicle.close()
        self.rsu.close()

    def wait_until_flowing(self, timeout_s: float = 10.0) -> None:
        """Put probes (seq < 0) until one crosses the relay."""
        deadline = time.monotonic() + timeout_s
        seq = -1
        while time.monotonic() < deadline:
            self.publisher.put(HEADER.pack(seq, time.time_ns()))
            probe_deadline = time.monotonic() + 0.5
            while time.monotonic() < probe_deadline:
                if self.received:
                    return
                time.sleep(0.01)
            seq -= 1
        raise RuntimeError("no probe crossed the relay")

    def send(self, rate_hz: float, duration_s: float, payload_bytes: int) -> dict[int, int]:
        """Put ``rate_hz * duration_s`` messages on an absolute schedule; seq -> send ns."""
        count, period_ns = round(rate_hz * duration_s), round(1e9 / rate_hz)
        padding = bytes(max(0, payload_bytes - HEADER.size))
        sent: dict[int, int] = {}
        start_ns = time.time_ns() + 10 * NS_PER_MS
        for seq in range(count):
            # Sleep to the next slot of the grid (never accumulates drift); a late slot is sent at once.
            remaining_ns = start_ns + seq * period_ns - time.time_ns()
            if remaining_ns > 0:
                time.sleep(remaining_ns / 1e9)
            send_ns = time.time_ns()
            self.publisher.put(HEADER.pack(seq, send_ns) + padding)
            sent[seq] = send_ns
        return sent

    def wait_for(self, count: int, timeout_s: float) -> None:
        """Wait until ``count`` numbered messages arrived or the deadline passed."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and self._numbered() < count:
            time.sleep(0.05)

    def _numbered(self) -> int:
        return sum(1 for _, payload in self.received if HEADER.unpack_from(payload)[0] >= 0)


# ---- the run ------------------------------------------------------------------------------


def _percentiles_ms(values_ns: np.ndarray) -> dict[str, float | int]:
    if values_ns.size == 0:
        return {"count": 0}
    p50, p95, p99 = np.percentile(values_ns, [50, 95, 99]) / NS_PER_MS
    return {"count": int(values_ns.size), "p50": round(float(p50), 3), "p95": round(float(p95), 3),
            "p99": round(float(p99), 3), "max": round(float(values_ns.max()) / NS_PER_MS, 3)}


def run(rate_hz: float, duration_s: float, profile: str, payload_bytes: int) -> dict:
    ctx = mp.get_context("spawn")  # a clean interpreter: no Zenoh runtime inherited by fork
    stop_mp = ctx.Event()
    results_rx, results_tx = ctx.Pipe(duplex=False)
    with Ends() as ends:
        config = LinkConfig(link_id="bench", rsu_connect=[ends.rsu_endpoint],
                            vehicle_connect=[ends.vehicle_endpoint], profile=profile, seed=0,
                            source_rate_hz=max(10 * rate_hz, 1000.0), source_burst=max(int(rate_hz), 200))
        relay = ctx.Process(target=_relay_process, args=(config.model_dump_json(), stop_mp, results_tx))
        relay.start()
        try:
            ends.wait_until_flowing()
            sent = ends.send(rate_hz, duration_s, payload_bytes)
            ends.wait_for(len(sent), timeout_s=5.0)
        finally:
            stop_mp.set()
            got = results_rx.recv() if results_rx.poll(15.0) else None
            relay.join(10.0)
            if relay.is_alive():
                relay.kill()
                relay.join()
        if got is None:
            raise RuntimeError("the relay process sent no results")
        return _summarise(sent, ends.received, got, rate_hz, duration_s, profile)


def _summarise(sent: dict[int, int], received: list[tuple[int, bytes]], relay_results: tuple,
               rate_hz: float, duration_s: float, profile: str) -> dict:
    """Percentiles of the drawn delay, the relay's lateness, both hops and the end-to-end error."""
    columns, relay_stats = relay_results
    seq, relay_rx, due, fired = (np.frombuffer(c, dtype=np.int64) for c in columns)
    numbered = seq >= 0
    seq, relay_rx, due, fired = seq[numbered], relay_rx[numbered], due[numbered], fired[numbered]
    row_of_seq = {s: i for i, s in enumerate(seq.tolist())}
    arrivals = [(row_of_seq[s], receive_ns) for receive_ns, payload in received
                if (s := HEADER.unpack_from(payload)[0]) in row_of_seq]
    rows = np.array([r for r, _ in arrivals], dtype=np.int64)
    vehicle_rx = np.array([t for _, t in arrivals], dtype=np.int64)
    send = np.array([sent[s] for s in seq.tolist()], dtype=np.int64)
    return {
        "rate_hz": rate_hz, "duration_s": duration_s, "profile": profile,
        "sent": len(sent), "received": int(rows.size),
        "drawn_delay_ms": _percentiles_ms(due - relay_rx),
        "lateness_ms": _percentiles_ms(fired - due),
        "rsu_to_relay_ms": _percentiles_ms(relay_rx - send),
        "fire_to_vehicle_ms": _percentiles_ms(vehicle_rx - fired[rows]),
        # receive - (send + drawn delay): everything the emulated link adds beyond its draw
        "end_to_end_error_ms": _percentiles_ms(vehicle_rx - (send[rows] + (due - relay_rx)[rows])),
        "relay_stats": relay_stats,
    }


def _print(result: dict) -> None:
    print(f"relay accuracy | profile {Path(result['profile']).stem} | {result['rate_hz']:g} msg/s for "
          f"{result['duration_s']:g} s | sent {result['sent']}, received {result['received']}")
    for name in ("drawn_delay_ms", "lateness_ms", "rsu_to_relay_ms", "fire_to_vehicle_ms", "end_to_end_error_ms"):
        p = result[name]
        if p["count"]:
            print(f"  {name:20s} p50 {p['p50']:8.3f}  p95 {p['p95']:8.3f}  p99 {p['p99']:8.3f}  max {p['max']:8.3f}")
    verdict = "met" if result["lateness_ms"].get("p99", float("inf")) <= TARGET_P99_MS else "MISSED"
    print(f"  target lateness p99 <= {TARGET_P99_MS} ms: {verdict}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate-hz", type=float, default=1000.0, help="messages per second (default %(default)s)")
    parser.add_argument("--duration-s", type=float, default=10.0, help="sending time in s (default %(default)s)")
    parser.add_argument("--payload-bytes", type=int, default=200, help="message size (default %(default)s)")
    parser.add_argument("--profile", help="link profile name or YAML (default: 40 ms + lognormal jitter)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        profile = args.profile
        if profile is None:
            profile = str(Path(tmp) / "bench-jitter.yaml")
            Path(profile).write_text(DEFAULT_PROFILE)
        result = run(args.rate_hz, args.duration_s, profile, args.payload_bytes)
    if args.json:
        json.dump(result, sys.stdout, indent=2)
        print()
    else:
        _print(result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
