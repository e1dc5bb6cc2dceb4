"""Latency budget of an RSU object list, stage by stage: RSU + link emulator + OBU on loopback.

Runs ``v2i demo`` (``v2i.orchestration.demo.Demo``: three service processes, scouting off, TCP on
127.0.0.1) for ``--duration`` s on ``--profile`` (default ``ideal``: no emulated delay, so what
remains is the software's) and prints each service's per-stage latency as it reports it
(``latency_ms`` of the RSU and OBU metrics and of the link stats; ``v2i.telemetry.latency``), with,
measured in the same run as references:

- ``raw hop``: a child process puts 1 kB messages at ``--hop-rate-hz`` on two publishers, the
  default one and an ``express`` one, to a subscriber session of this process (this process
  listens, the child connects, as the link emulator connects to the RSU); one-way delay =
  receive - send, both ``time.time_ns`` of this host (one clock, no synchronisation error);
- ``rsu -> probe``: the RSU's object lists as a plain subscriber connected to the RSU sees
  them: receive - header publish stamp (the RSU's clock is the host's: the run has no clock
  offset or drift), i.e. the RSU's ``stamp_to_put`` plus one Zenoh hop;
- the OBU's own view: ``rsus[].delay_p50_ms`` / ``delay_p95_ms`` of its last metrics (RSU
  publish stamp -> OBU receive through its clock estimate, over its 10 s window) and the
  report's clock-offset error (which that estimate carries).

The run starts when every service is ready (``v2i.orchestration.children``: ``--ready-timeout``, default
120 s); the hop sender puts from the demo's launch until it ends.

    python benchmarks/latency_budget.py [--duration 20] [--profile ideal] [--hop-rate-hz 20] [--ready-timeout S] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import struct
import subprocess
import sys
import threading
import time

import numpy as np
import zenoh

from v2i.orchestration.children import READY_TIMEOUT_S
from v2i.orchestration.demo import Demo
from v2i.offline.spec import RunSpec
from schemas import keys
from schemas.codec import header_of, open_body
from schemas.messages import ObjectList, ObuMetrics
from schemas.codec import decode
from v2i.runtime.process import stop_on_signals
from v2i.runtime.transport import free_tcp_endpoint, open_session

HOP_KEYS = {"default": "v2x/bench/hop/default", "express": "v2x/bench/hop/express"}
HOP_BYTES = 1024
STAMP = struct.Struct("<q")  # time.time_ns at the put


def hop_sender(endpoint: str, rate_hz: float, duration_s: float) -> None:
    """Child process: put stamped messages alternately on the default and the express publisher,
    for ``duration_s`` or until SIGTERM / SIGINT."""
    stop = stop_on_signals()
    session = open_session(connect=[endpoint])
    pubs = {"default": session.declare_publisher(HOP_KEYS["default"]),
            "express": session.declare_publisher(HOP_KEYS["express"], express=True)}
    padding = bytes(HOP_BYTES - STAMP.size)
    period_s, end = 1.0 / rate_hz, time.monotonic() + duration_s
    next_t = time.monotonic()
    try:
        while (now := time.monotonic()) < end and not stop.is_set():
            if now < next_t:
                stop.wait(next_t - now)
            for pub in pubs.values():
                pub.put(STAMP.pack(time.time_ns()) + padding)
            next_t += period_s
    finally:
        for pub in pubs.values():
            pub.undeclare()
        session.close()


class HopReceiver:
    """This process's end of the raw hop: one session listening, one subscriber per publisher kind."""

    def __init__(self, endpoint: str) -> None:
        self.delays_ms: dict[str, list[float]] = {kind: [] for kind in HOP_KEYS}
        self._session = open_session(listen=[endpoint])
        self._subs = [self._session.declare_subscriber(key, lambda s, k=kind: self._on(k, s))
                      for kind, key in HOP_KEYS.items()]

    def _on(self, kind: str, sample: zenoh.Sample) -> None:
        receive_ns = time.time_ns()
        (send_ns,) = STAMP.unpack_from(sample.payload.to_bytes())
        self.delays_ms[kind].append((receive_ns - send_ns) / 1e6)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._session.close()


class BudgetDemo(Demo):
    """The demo, keeping the OBU's last metrics and probing the RSU's lists one hop from the RSU."""

    def __init__(self, spec: RunSpec, ready_timeout_s: float) -> None:
        super().__init__(spec, ready_timeout_s=ready_timeout_s)
        self.last_obu_metrics: ObuMetrics | None = None
        self.probe_ms: list[float] = []
        self._probe = open_session(connect=[self.rsu_ep])  # retries until the RSU listens
        self._probe_sub = self._probe.declare_subscriber(keys.rsu_objects(spec.rsu_config().rsu_id), self._on_list)

    def _on_list(self, sample: zenoh.Sample) -> None:
        receive_ns = time.time_ns()
        header = header_of(open_body(sample.payload.to_bytes(), ObjectList))
        self.probe_ms.append((receive_ns - header.publish_time_ns) / 1e6)

    def _score(self, kind: str, data: bytes) -> None:
        super()._score(kind, data)
        if kind == "metrics":
            self.last_obu_metrics = decode(data, ObuMetrics)

    def close_probe(self) -> None:
        self._probe_sub.undeclare()
        self._probe.close()


def quantiles_ms(values: list[float]) -> dict[str, float | int]:
    if not values:
        return {"count": 0, "p50": None, "p95": None, "p99": None}
    p50, p95, p99 = np.percentile(values, [50, 95, 99])
    return {"count": len(values), "p50": round(p50, 3), "p95": round(p95, 3), "p99": round(p99, 3)}


def run(args: argparse.Namespace) -> dict:
    spec = RunSpec(profile=args.profile, scenario=args.scenario, duration_s=args.duration, seed=args.seed)
    if spec.rsu_clock_offset_ms or spec.rsu_clock_drift_ppm:
        raise SystemExit("the probe reads the RSU's publish stamp as host time: no clock offset or drift")
    hop_ep = free_tcp_endpoint()
    receiver = HopReceiver(hop_ep)
    demo = BudgetDemo(spec, args.ready_timeout)
    # the sender puts until the demo ends (it is stopped then), at most for the longest the demo can take
    longest_s = args.ready_timeout + 5.0 + args.duration
    sender = subprocess.Popen([sys.executable, __file__, "--hop-sender", hop_ep, "--hop-rate-hz", str(args.hop_rate_hz),
                               "--duration", str(longest_s)])
    try:
        report = demo.run()
    finally:
        sender.terminate()
        sender.wait(30)
        demo.close_probe()
        receiver.close()
    rsus = demo.last_obu_metrics.rsus if demo.last_obu_metrics is not None else ()
    return {
        "profile": args.profile, "duration_s": args.duration,
        "latency_ms": report["latency_ms"],
        "reference_ms": {
            **{f"raw_hop_{kind}": quantiles_ms(v[1:]) for kind, v in receiver.delays_ms.items()},  # 1st: route set-up
            "rsu_to_probe": quantiles_ms(demo.probe_ms),
        },
        "obu_link_status": [{"rsu_id": r.rsu_id, "delay_p50_ms": r.delay_p50_ms, "delay_p95_ms": r.delay_p95_ms}
                            for r in rsus],
        "clock_offset_error_ms": report["clock_offset_error_ms"],
        "output_deadline_miss_ratio": report["output_deadline_miss_ratio"], "outputs": report["outputs"],
        "cycles": report["cycles"],
    }


def table(result: dict) -> str:
    lines = [f"latency budget, profile {result['profile']}, {result['duration_s']} s (ms)",
             f"{'service':8s} {'stage':14s} {'count':>6s} {'p50':>8s} {'p95':>8s} {'p99':>8s}"]

    def row(service: str, stage: str, q: dict) -> str:
        cells = [f"{q[k]:8.3f}" if q[k] is not None else f"{'-':>8s}" for k in ("p50", "p95", "p99")]
        return f"{service:8s} {stage:14s} {q['count']:6d} {' '.join(cells)}"

    for service in ("rsu", "link", "obu"):
        for stage, q in result["latency_ms"].get(service, {}).items():
            lines.append(row(service, stage, q))
    for name, q in result["reference_ms"].items():
        lines.append(row("ref", name, q))
    for r in result["obu_link_status"]:
        lines.append(f"OBU link status {r['rsu_id']}: delay p50 {r['delay_p50_ms']} ms, p95 {r['delay_p95_ms']} ms")
    c = result["clock_offset_error_ms"]
    lines.append(f"clock offset error p50 {c['p50']} ms, p95 {c['p95']} ms; "
                 f"output deadline misses {result['output_deadline_miss_ratio']:.1%} ({result['outputs']} outputs, "
                 f"{result['cycles']} cycles)")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--profile", default="ideal")
    parser.add_argument("--scenario", default="red-light-runner")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--hop-rate-hz", type=float, default=20.0)
    parser.add_argument("--ready-timeout", type=float, default=READY_TIMEOUT_S,
                        help="s every service may take to be ready (default %(default)s); the run starts when all are")
    parser.add_argument("--json", help="also write the result as JSON to this file")
    parser.add_argument("--hop-sender", help=argparse.SUPPRESS)  # the child process's endpoint
    args = parser.parse_args()
    if args.hop_sender:
        hop_sender(args.hop_sender, args.hop_rate_hz, args.duration)
        return
    result = run(args)
    print(table(result))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
