"""Scale: one live OBU fusing K RSUs x N objects at 10 Hz (issue 12).

    python benchmarks/scale.py                        # K in 1,2,4,8 x N in 50,100,200, 15 s each
    python benchmarks/scale.py --k 8 --n 100 --measure-s 30
    python benchmarks/scale.py --k 8 --n 200 --profile-obu /tmp/obu.prof   # the OBU under cProfile

Per (K, N) it starts two processes on free tcp/127.0.0.1 ports, scouting off, connected
directly (no link emulator, so the OBU is what is measured):

- ``v2i obu`` (sim source for its own LiDAR and pose, the bundled ``--scenario``), with the K
  RSUs registered as ``known_rsus`` (a ``--config`` YAML) and every other setting default;
- one synthetic RSU process (this script, ``publish``) serving all K RSU ids: one process,
  not K, so that on the 2 shared cores K Python interpreters do not compete with the OBU
  for CPU; on the wire it is the same (K keys, K queryables, K clocks). Each RSU publishes an
  ``ObjectList`` of N objects on ``v2x/rsu/{id}/objects`` at ``--rsu-rate-hz`` (capture
  phases spread over the period: unsynchronised RSUs), ``--rsu-latency-ms`` after capture,
  stamped by its own clock (offset (k + 1) * 3.7 ms), and answers the OBU's time queries on
  ``v2x/rsu/{id}/time`` (``rsu_service.pipeline.answer_time_request``). The objects circle
  the ego on its true path (8-60 m from it), so they stay on site; with
  ``--objects shared`` every RSU sees the same N objects (one site, overlapping views, own
  noise), with ``distinct`` each RSU has its own N.

Both run with ``--await-start`` (``v2i.orchestration.children``): the scenario starts once both are
ready and this process is subscribed. This process subscribes to the OBU's ``objects`` and
``metrics``. The cycle compute time is
what the OBU stamps: its metrics message of cycle s is stamped (``t_ns``) after the cycle's
fuse, encode and put of the fused list, whose ``publish_time_ns`` is taken just before fuse
(``obu_service.node.ObuNode._publish``), so compute = metrics.t_ns - objects.publish_time_ns
for metrics.cycles == objects.seq: fuse + encode + publish, in the OBU's clock. Cycles,
misses and compute are counted over the cycles captured in [start + warm-up, + measure);
lists sent / accepted / refused over the whole run; CPU % (of one core) and RSS from /proc
over the window; ``host`` is the whole machine's CPU use (2 cores = 200 %), since others share it.
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from v2i.orchestration.children import READY_TIMEOUT_S, Child, start_all, wait_ready

PERIOD_NS = 100_000_000  # the OBU's 10 Hz cycle
SITE_RADIUS_M = 60.0  # objects circle the ego within this
MIN_RANGE_M = 8.0  # and no closer (never on the ego itself)
CLOCK_OFFSET_STEP_NS = 3_700_000  # RSU k's clock runs (k + 1) * this ahead of the true clock


# --- the synthetic RSUs (child process: ``scale.py publish ...``) -----------------------
class Site:
    """N objects, each on a circle around the ego: p(t) = e(t) + r u(w t + phi), u(a) = (cos a, sin a),
    v = e'(t) + r w u'(w t + phi), centripetal a = -r w^2 u; r in [MIN_RANGE_M, SITE_RADIUS_M]
    (uniform over the annulus), tangential speed 1-8 m/s either way."""

    def __init__(self, world, n: int, rng: np.random.Generator):
        self.world, self.n = world, n
        self.r_m = np.sqrt(rng.uniform(MIN_RANGE_M**2, SITE_RADIUS_M**2, n))  # (N,) circle radius
        self.w_rps = rng.choice([-1.0, 1.0], n) * rng.uniform(1.0, 8.0, n) / self.r_m  # (N,) angular speed
        self.phi = rng.uniform(0, 2 * np.pi, n)
        self.cls = rng.choice([1, 1, 1, 2, 5, 6], n)  # mostly cars
        self.lwh = np.array([[4.5, 1.8, 1.5], [5.5, 2.0, 2.2], [0, 0, 0], [0, 0, 0], [0.6, 0.6, 1.7],
                             [1.8, 0.6, 1.7]])[self.cls - 1]

    def objects_at(self, t_s: float, rng: np.random.Generator, std_m: float = 0.3, v_std_mps: float = 0.3):
        """ObjectArray (map frame) of the N objects at scenario time t_s as one RSU sees them."""
        from v2i.core.objects import ObjectArray

        ego = self.world.ego_at(t_s)
        a = self.w_rps * t_s + self.phi
        u, du = np.column_stack([np.cos(a), np.sin(a)]), np.column_stack([-np.sin(a), np.cos(a)])
        xy = np.array([ego.x, ego.y]) + self.r_m[:, None] * u
        vxy = np.array([ego.vx, ego.vy]) + (self.r_m * self.w_rps)[:, None] * du
        n = self.n
        return ObjectArray(
            ids=np.arange(1, n + 1), cls=self.cls, xy=xy + rng.normal(0, std_m, (n, 2)), z=self.lwh[:, 2] / 2,
            lwh=self.lwh, yaw=np.arctan2(vxy[:, 1], vxy[:, 0]), vxy=vxy + rng.normal(0, v_std_mps, (n, 2)),
            axy=-(self.r_m * self.w_rps**2)[:, None] * u, cov_xy=np.tile(np.eye(2) * std_m**2, (n, 1, 1)),
            cov_vxy=np.tile(np.eye(2) * v_std_mps**2, (n, 1, 1)), confidence=np.full(n, 0.9))


class Rsus:
    """K synthetic RSUs in one Zenoh session: object lists on a schedule, time replies in the callback."""

    def __init__(self, args, session):
        from v2i.sim.scenario import load_scenario
        from v2i.sim.world import World

        world = World(load_scenario(args.scenario))
        self.ids, self.args, self.session = args.ids.split(","), args, session
        k = len(self.ids)
        seeds = np.random.SeedSequence(args.seed).spawn(2 * k)
        self.noise = [np.random.default_rng(s) for s in seeds[:k]]
        shared = Site(world, args.n, np.random.default_rng(seeds[k]))
        self.sites = [shared if args.objects == "shared" else Site(world, args.n, np.random.default_rng(s))
                      for s in seeds[k:]]
        self.offset_ns = [(i + 1) * CLOCK_OFFSET_STEP_NS for i in range(k)]
        self.sent, self.skipped, self.replies, self.late_ms = [0] * k, 0, 0, []
        self.lock = threading.Lock()

    def on_query(self, index: int, query) -> None:
        from rsu_service.pipeline import answer_time_request
        from schemas import keys
        from schemas.codec import CodecError, decode, encode
        from schemas.messages import TimeRequest

        t2_ns = time.time_ns() + self.offset_ns[index]
        try:
            request = decode(query.payload.to_bytes(), TimeRequest)
        except (CodecError, AttributeError):
            return
        rsu_id = self.ids[index]
        reply = answer_time_request(request, rsu_id, t2_ns, time.time_ns() + self.offset_ns[index])
        query.reply(keys.rsu_time(rsu_id), encode(reply))
        with self.lock:
            self.replies += 1

    def schedule(self, start_ns: int) -> list[tuple[int, int, int]]:
        """(publish true ns, RSU index, capture true ns) of every list from time zero ``start_ns``, as a heap."""
        period_ns = round(1e9 / self.args.rate_hz)
        latency_ns = round(self.args.latency_ms * 1e6)
        end_ns = start_ns + round(self.args.duration_s * 1e9)
        events = []
        for i in range(len(self.ids)):
            phase_ns = i * period_ns // len(self.ids)
            for capture_ns in range(start_ns + phase_ns, end_ns, period_ns):
                events.append((capture_ns + latency_ns, i, capture_ns))
        heapq.heapify(events)
        return events

    def run(self, stop: threading.Event) -> None:
        from v2i.fusion.wire import states_from_objects
        from schemas import keys
        from schemas.codec import encode
        from schemas.messages import ObjectList, ObjectListHeader
        from v2i.runtime.process import read_start_line

        pubs = [self.session.declare_publisher(keys.rsu_objects(r)) for r in self.ids]
        queryables = [self.session.declare_queryable(keys.rsu_time(r), lambda q, i=i: self.on_query(i, q))
                      for i, r in enumerate(self.ids)]
        print(json.dumps({"event": "ready", "service": "scale-rsus"}), flush=True)
        start_ns = read_start_line("rsus", stop)
        events, period_ns = [] if start_ns is None else self.schedule(start_ns), round(1e9 / self.args.rate_hz)
        while events and not stop.is_set():
            due_ns, i, capture_ns = heapq.heappop(events)
            stop.wait(max(due_ns - time.time_ns(), 0) * 1e-9)
            late_ns = time.time_ns() - due_ns
            if late_ns > period_ns:  # behind by a period: skip, never send a burst of old lists
                self.skipped += 1
                continue
            objs = self.sites[i].objects_at((capture_ns - start_ns) * 1e-9, self.noise[i])
            header = ObjectListHeader(rsu_id=self.ids[i], seq=self.sent[i], capture_time_ns=capture_ns + self.offset_ns[i],
                                      publish_time_ns=time.time_ns() + self.offset_ns[i], sensor="synthetic")
            pubs[i].put(encode(ObjectList(header=header, objects=states_from_objects(objs))))
            self.sent[i] += 1
            self.late_ms.append((time.time_ns() - due_ns) * 1e-6)
        for entity in pubs + queryables:
            entity.undeclare()


def publish_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="scale.py publish")
    p.add_argument("--ids", required=True)
    for name, kind in (("n", int), ("rate-hz", float), ("latency-ms", float), ("duration-s", float), ("seed", int)):
        p.add_argument(f"--{name}", type=kind, required=True)
    p.add_argument("--listen", required=True)
    p.add_argument("--scenario", required=True)
    p.add_argument("--objects", choices=("shared", "distinct"), required=True)
    args = p.parse_args(argv)
    from v2i.runtime.process import stop_on_signals
    from v2i.runtime.transport import open_session

    stop = stop_on_signals()
    session = open_session([args.listen], [])
    try:
        rsus = Rsus(args, session)
        rsus.run(stop)
    finally:
        session.close()
    late = np.array(rsus.late_ms or [0.0])
    print(json.dumps({"event": "done", "sent": sum(rsus.sent), "skipped": rsus.skipped, "time_replies": rsus.replies,
                      "late_p99_ms": float(np.percentile(late, 99))}), flush=True)
    return 0


# --- /proc ------------------------------------------------------------------------------
def cpu_ticks(pid: int) -> int:
    """utime + stime of ``pid`` (clock ticks)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])  # fields 14 and 15 of stat(5), after "(comm)"


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def host_ticks() -> tuple[int, int]:
    """(busy, total) clock ticks of the whole machine (/proc/stat; idle and iowait are not busy)."""
    values = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    total = sum(values[:8])
    return total - values[3] - values[4], total


class Usage:
    """CPU % (of one core) of given pids and of the host between ``start`` and ``stop``."""

    def __init__(self, pids: dict[str, int]):
        self.pids, self.tck = pids, os.sysconf("SC_CLK_TCK")

    def start(self) -> None:
        self.t0, self.ticks0, self.host0 = time.monotonic(), {n: cpu_ticks(p) for n, p in self.pids.items()}, host_ticks()

    def stop(self) -> dict[str, float]:
        wall_s = time.monotonic() - self.t0
        out = {f"{n}_cpu": 100.0 * (cpu_ticks(p) - self.ticks0[n]) / self.tck / wall_s for n, p in self.pids.items()}
        out.update({f"{n}_rss_mb": rss_mb(p) for n, p in self.pids.items()})
        busy, total = host_ticks()
        out["host_cpu"] = 100.0 * os.cpu_count() * (busy - self.host0[0]) / max(total - self.host0[1], 1)
        return out


# --- one run ------------------------------------------------------------------------------
def stop_all(procs: list[Child]) -> None:
    """SIGINT to each child this script started (by pid), then SIGKILL after 10 s."""
    for child in procs:
        if child.proc.poll() is None:
            child.proc.send_signal(signal.SIGINT)
    for child in procs:
        child.stop(signal.SIGINT, timeout_s=10.0)


def done_event(child: Child, timeout_s: float = 10.0) -> dict:
    """The publisher's closing counts."""
    while (event := child.events.get(timeout=timeout_s)).get("event") != "done":
        pass
    return event


class Collector:
    """Raw payloads of the OBU's fused lists and metrics (callbacks only append)."""

    def __init__(self, obu_endpoint: str, vehicle_id: str):
        from schemas import keys
        from v2i.runtime.transport import open_session

        self.objects, self.metrics = [], []
        self.session = open_session([], [obu_endpoint])
        self.subs = [
            self.session.declare_subscriber(keys.obu_objects(vehicle_id), lambda s: self.objects.append(s.payload.to_bytes())),
            self.session.declare_subscriber(keys.obu_metrics(vehicle_id), lambda s: self.metrics.append(s.payload.to_bytes()))]

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.session.close()


def sleep_until_ns(t_ns: int) -> None:
    time.sleep(max(t_ns - time.time_ns(), 0) * 1e-9)


def site_rsus(scenario: str, k: int) -> dict[str, list[float]]:
    """K RSU ids -> map positions on a 40 m ring around the ego's start (the OBU's known_rsus)."""
    from v2i.sim.scenario import load_scenario
    from v2i.sim.world import World

    ego = World(load_scenario(scenario)).ego_at(0.0)
    angles = 2 * np.pi * np.arange(k) / k
    return {f"rsu-{i}": [round(ego.x + 40 * np.cos(a), 2), round(ego.y + 40 * np.sin(a), 2)] for i, a in enumerate(angles)}


def run_one(k: int, n: int, args, procs: list[Child], tmp: Path) -> dict:
    """Start the K-RSU publisher and the OBU, measure the window, stop both; the row's numbers."""
    from v2i.runtime.transport import free_tcp_endpoint

    obu_ep, rsu_ep = free_tcp_endpoint(), free_tcp_endpoint()
    rsus = site_rsus(args.scenario, k)
    budget = {"max_rsu_objects_per_cycle": args.max_rsu_objects} if args.max_rsu_objects else {}
    (tmp / "obu.yaml").write_text(json.dumps({"known_rsus": rsus, **budget}))  # JSON is YAML
    run_s = args.warmup_s + args.measure_s + 2.0
    common = ["--scenario", args.scenario, "--seed", str(args.seed)]
    publisher = Child("rsus", [sys.executable, __file__, "publish", "--ids", ",".join(rsus), "--n", str(n), "--rate-hz",
                               str(args.rsu_rate_hz), "--latency-ms", str(args.rsu_latency_ms), "--duration-s",
                               str(run_s), "--listen", rsu_ep, "--objects", args.objects, *common])
    procs.append(publisher)
    wait_ready([publisher], args.ready_timeout)  # it listens before the OBU connects
    profile = ["-m", "cProfile", "-o", args.profile_obu] if args.profile_obu else []
    obu = Child("obu", [sys.executable, *profile, "-m", "v2i", "obu", "--listen", obu_ep, "--connect", rsu_ep, "--config",
                        str(tmp / "obu.yaml"), "--duration", str(run_s), "--await-start", *common], label="obu ego")
    procs.append(obu)
    wait_ready([obu], args.ready_timeout)
    collector = Collector(obu_ep, "ego")
    start_at_ns = start_all([publisher, obu])
    window_ns = (start_at_ns + round(args.warmup_s * 1e9), start_at_ns + round((args.warmup_s + args.measure_s) * 1e9))
    try:
        sleep_until_ns(window_ns[0])
        usage = Usage({"obu": obu.proc.pid, "rsus": publisher.proc.pid, "bench": os.getpid()})
        usage.start()
        sleep_until_ns(window_ns[1])
        used = usage.stop()
        time.sleep(0.5)  # the window's last cycle is published up to 100 ms after its capture
        stop_all([publisher])
        time.sleep(0.5)  # the OBU takes the last lists and reports them in its next cycles' metrics
    finally:
        collector.close()
        stop_all([publisher, obu])
    done = done_event(publisher)
    stopped = [line for line in obu.stderr_tail if "stopped:" in line]
    row = summarise(collector.objects, collector.metrics, window_ns)
    row.update(used, k=k, n=n, sent=done["sent"], rsu_skipped=done["skipped"], rsu_late_p99_ms=done["late_p99_ms"],
               obu_stopped=stopped[-1] if stopped else "")
    return row


def summarise(objects: list[bytes], metrics: list[bytes], window_ns: tuple[int, int]) -> dict:
    """Cycles, misses, compute and E2E percentiles over the window; accepted / refused overall."""
    from schemas.codec import decode, object_count, open_body
    from schemas.messages import FusedObjectList, ObuMetrics

    cycles = {}  # seq -> (cycle_time_ns, publish_time_ns, objects out)
    for payload in objects:
        body = open_body(payload, FusedObjectList)
        cycles[body["seq"]] = (body["cycle_time_ns"], body["publish_time_ns"], object_count(body))
    ms = sorted((decode(p, ObuMetrics) for p in metrics), key=lambda m: m.cycles)
    inside = {s for s, (t, _, _) in cycles.items() if window_ns[0] <= t < window_ns[1]}
    before = [m for m in ms if m.cycles < min(inside)]
    last = max((m for m in ms if m.cycles in inside), key=lambda m: m.cycles)
    first = before[-1] if before else ObuMetrics(vehicle_id="ego", t_ns=last.t_ns)
    compute_ms = np.array([(m.t_ns - cycles[m.cycles][1]) * 1e-6 for m in ms if m.cycles in inside])
    e2e_ms = np.array([(cycles[s][1] - cycles[s][0]) * 1e-6 for s in inside])
    modes = {m: last.mode_counts.get(m, 0) - first.mode_counts.get(m, 0) for m in last.mode_counts}
    final = ms[-1]
    return {
        "cycles": last.cycles - first.cycles, "misses": last.output_deadline_misses - first.output_deadline_misses,
        "compute_p50_ms": float(np.percentile(compute_ms, 50)), "compute_p99_ms": float(np.percentile(compute_ms, 99)),
        "compute_max_ms": float(compute_ms.max()), "compute_samples": len(compute_ms),
        "compute_ms": compute_ms.round(3).tolist(), "e2e_p99_ms": float(np.percentile(e2e_ms, 99)),
        "out_objects": int(np.median([cycles[s][2] for s in inside])), "modes": {m: c for m, c in modes.items() if c},
        "accepted": sum(r.messages_accepted for r in final.rsus), "refused": dict(final.rejected),
        "output_dropped": dict(final.output_dropped)}


# --- the table ----------------------------------------------------------------------------
COLUMNS = (("K", "k", "{:d}"), ("N", "n", "{:d}"), ("cycles", "cycles", "{:d}"), ("miss", "misses", "{:d}"),
           ("p50 ms", "compute_p50_ms", "{:.2f}"), ("p99 ms", "compute_p99_ms", "{:.2f}"),
           ("max ms", "compute_max_ms", "{:.2f}"), ("e2e p99", "e2e_p99_ms", "{:.1f}"),
           ("out", "out_objects", "{:d}"), ("sent", "sent", "{:d}"), ("accepted", "accepted", "{:d}"),
           ("refused", "refused_total", "{:d}"), ("obu cpu%", "obu_cpu", "{:.0f}"), ("obu MB", "obu_rss_mb", "{:.0f}"),
           ("rsus cpu%", "rsus_cpu", "{:.0f}"), ("rsus MB", "rsus_rss_mb", "{:.0f}"),
           ("bench cpu%", "bench_cpu", "{:.0f}"), ("host cpu%", "host_cpu", "{:.0f}"))


def table_line(values: list[str]) -> str:
    return " ".join(f"{v:>{max(len(c[0]), 6)}}" for v, c in zip(values, COLUMNS))


def print_row(row: dict) -> None:
    row["refused_total"] = sum(row["refused"].values())
    print(table_line([fmt.format(row[key]) for _, key, fmt in COLUMNS]), flush=True)


def print_notes(rows: list[dict]) -> None:
    for row in rows:
        print(f"K={row['k']} N={row['n']}: modes {row['modes']}, refused {row['refused'] or '{}'}, output dropped "
              f"{row['output_dropped'] or '{}'}, compute samples {row['compute_samples']}, RSU lists skipped "
              f"{row['rsu_skipped']}, publisher late p99 {row['rsu_late_p99_ms']:.1f} ms")


def parse_list(text: str) -> list[int]:
    return [int(v) for v in text.split(",") if v]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["publish"]:
        return publish_main(argv[1:])
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--k", type=parse_list, default=[1, 2, 4, 8], help="RSU counts (default 1,2,4,8)")
    p.add_argument("--n", type=parse_list, default=[50, 100, 200], help="objects per RSU list (default 50,100,200)")
    p.add_argument("--warmup-s", type=float, default=5.0, help="after the scenario start, not measured (default 5)")
    p.add_argument("--measure-s", type=float, default=15.0, help="measured window (default 15)")
    p.add_argument("--ready-timeout", type=float, default=READY_TIMEOUT_S,
                   help="s each process may take to be ready (default %(default)s); the scenario starts when both are")
    p.add_argument("--rsu-rate-hz", type=float, default=10.0, help="object lists per second per RSU (default 10)")
    p.add_argument("--rsu-latency-ms", type=float, default=30.0, help="RSU capture -> publish (default 30)")
    p.add_argument("--objects", choices=("shared", "distinct"), default="shared",
                   help="every RSU sees the same N objects (default) or its own N")
    p.add_argument("--scenario", default="red-light-runner", help="bundled scenario of the OBU's own sensing")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-rsu-objects", type=int, help="the OBU's max_rsu_objects_per_cycle (default: its own, "
                   "1024; K x N above it is refused as rsu_objects_over_budget)")
    p.add_argument("--profile-obu", metavar="FILE", help="run the OBU under cProfile, stats to FILE (last run's)")
    p.add_argument("--json", metavar="FILE", help="write every row here")
    args = p.parse_args(argv)
    for signum in (signal.SIGINT, signal.SIGTERM):  # even where started with SIGINT ignored (a shell's &)
        signal.signal(signum, signal.default_int_handler)
    if args.profile_obu:
        args.profile_obu = str(Path(args.profile_obu).resolve())
    print(f"one OBU, K RSUs x N objects ({args.objects}) at {args.rsu_rate_hz:g} Hz each, {args.measure_s:g} s "
          f"after {args.warmup_s:g} s warm-up; compute = fuse + encode + publish per cycle; cpu% of one core")
    print(table_line([c[0] for c in COLUMNS]), flush=True)
    rows, procs = [], []
    try:
        with tempfile.TemporaryDirectory(prefix="v2i-scale-") as tmp:
            for k in args.k:
                for n in args.n:
                    rows.append(run_one(k, n, args, procs, Path(tmp)))
                    print_row(rows[-1])
    finally:
        stop_all(procs)
    print_notes(rows)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
