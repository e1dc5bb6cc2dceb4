"""Scale benchmark, serving half: one RSU and one link emulator serving V vehicles.

    python benchmarks/scale_vehicles.py                          # V = 1 5 10 20, real v2i obu processes
    python benchmarks/scale_vehicles.py --mode light --vehicles 1 5 10 20 --measure-s 10

For each V: one ``v2i rsu`` (sim source, ``--scenario``, clock offset and drift 0), one
``v2i link`` with ``--vehicle carK=EP_K,TAP_K`` per vehicle (one channel per RSU-vehicle pair,
``--profile``), and V vehicles, each a process listening on its own endpoint EP_K:

- ``--mode obu``: a real ``v2i obu`` (time sync at 10 Hz, LiDAR, fusion, pose at 10 Hz);
- ``--mode light``: a light vehicle (this script's ``light-vehicle``) that answers like an
  OBU on the wire: decodes every RSU list, sends a ``TimeRequest`` at 10 Hz and publishes an
  ``EgoPose`` at 10 Hz, ``--light-distance-m`` east of the RSU, but runs no perception.

Every process gets explicit tcp/127.0.0.1 ports (scouting is off in ``open_session``). RSU and
vehicles run with ``--await-start`` (``v2i.orchestration.children``): the scenario starts when every
process is ready and the taps listen, however long the V processes took to start. What
each vehicle's channel delivers is measured by a tap: a session of this script listening on
TAP_K, to which the emulator's session for vehicle K also connects, so it hears exactly the
puts vehicle K gets. A monitor connected to the RSU hears every list the RSU publishes.

Per vehicle, over lists published in the measurement window (RSU publish time):
received / expected, and the delay as delivered, tap receive time - RSU ``publish_time_ns``
(one host clock, the RSU's offset and drift 0), p50 / p95 in ms. Per process: CPU % over the
window (utime + stime from /proc/PID/stat) and RSS (VmRSS) at its end. "Served" means the
vehicle's received ratio is no more than 3 binomial standard deviations below the profile's
declared delivery ratio (``validate.declared_loss`` at the vehicles' distance). Only the
processes started here are stopped, by pid.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import queue
import sys
import threading
import time
from pathlib import Path

import numpy as np

from v2i.orchestration.children import READY_TIMEOUT_S, Child, start_all, wait_ready
from link_emulator.profile import load_profile
from link_emulator.validate import Settings, declared_loss
from schemas import keys
from schemas.codec import CodecError, decode, encode
from schemas.messages import EgoPose, ObjectList, TimeRequest
from v2i.runtime.process import read_start_line
from v2i.runtime.transport import free_tcp_endpoint, open_session
from v2i.sim.scenario import load_scenario

RSU_ID = "rsu1"
LINK_ID = "scale1"
SETTLE_S = 2.0  # measurement starts this long after the scenario start
TICKS_PER_S = os.sysconf("SC_CLK_TCK")


# ---- a light vehicle: the OBU's wire behaviour without its perception --------------------

def light_vehicle(args: argparse.Namespace) -> int:
    """Listen on ``--listen``; say ready; on the start line, decode RSU lists, ask the time and publish
    a pose at 10 Hz until time zero + ``--duration``."""
    session = open_session(listen=[args.listen])
    lists = {"received": 0, "undecodable": 0, "time_replies": 0}

    def on_list(sample) -> None:
        try:
            decode(sample.payload.to_bytes(), ObjectList)
            lists["received"] += 1
        except CodecError:
            lists["undecodable"] += 1

    sub = session.declare_subscriber(keys.RSU_OBJECTS_ALL, on_list)
    pose_pub = session.declare_publisher(keys.obu_pose(args.vehicle_id))
    queries = 0

    def on_reply(reply) -> None:
        lists["time_replies"] += reply.ok is not None

    print(json.dumps({"event": "ready"}), flush=True)
    start_ns = read_start_line(f"light {args.vehicle_id}", threading.Event())
    if start_ns is None:  # stopped before the start
        sub.undeclare()
        pose_pub.undeclare()
        session.close()
        return 0
    end_ns = start_ns + round(args.duration * 1e9)
    seq = 0
    while (now_ns := time.time_ns()) < end_ns:
        seq += 1
        pose_pub.put(encode(EgoPose(vehicle_id=args.vehicle_id, t_ns=now_ns, x=args.x, y=args.y)))
        request = encode(TimeRequest(obu_id=args.vehicle_id, seq=seq, t1_ns=now_ns))
        session.get(keys.rsu_time(RSU_ID), on_reply, payload=request, timeout=2.0)
        queries += 1
        time.sleep(max(0.0, 0.1 - (time.time_ns() - now_ns) * 1e-9))
    time.sleep(0.5)  # the last replies
    pose_pub.undeclare()
    sub.undeclare()
    session.close()
    print(json.dumps({"event": "done", **lists, "time_queries": queries}), flush=True)
    return 0


# ---- processes ------------------------------------------------------------------------------

def done_line(child: Child, timeout_s: float) -> dict:
    """The light vehicle's closing counts ({} if none came)."""
    deadline = time.monotonic() + timeout_s
    while (remaining_s := deadline - time.monotonic()) > 0:
        try:
            event = child.events.get(timeout=remaining_s)
        except queue.Empty:
            break
        if event.get("event") == "done":
            return event
    return {}


def cpu_ticks(pid: int) -> int | None:
    """utime + stime of ``pid`` in clock ticks, None once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return None
    return int(fields[11]) + int(fields[12])  # fields 14 and 15 of proc(5), counted after "(comm)"


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


# ---- taps -------------------------------------------------------------------------------------

class Taps:
    """A monitor on the RSU (lists published: seq -> publish ns) and one tap per vehicle
    (seq -> first receive ns); callbacks only stamp and enqueue raw payloads."""

    def __init__(self, rsu_ep: str, tap_eps: dict[str, str]) -> None:
        self.inbox: queue.Queue = queue.Queue()
        self.published: dict[int, int] = {}
        self.received: dict[str, dict[int, int]] = {vid: {} for vid in tap_eps}
        self.link_stats: dict = {}  # the emulator's latest stats, heard on the first tap
        self.sessions = [open_session(listen=[ep]) for ep in tap_eps.values()]
        self.subs = [s.declare_subscriber(keys.RSU_OBJECTS_ALL,
                                          lambda smp, vid=vid: self.inbox.put((vid, time.time_ns(), smp.payload.to_bytes())))
                     for vid, s in zip(tap_eps, self.sessions)]
        self.subs.append(self.sessions[0].declare_subscriber(keys.link_stats(LINK_ID), self._on_stats))
        self.sessions.append(open_session(connect=[rsu_ep]))
        self.subs.append(self.sessions[-1].declare_subscriber(
            keys.rsu_objects(RSU_ID), lambda smp: self.inbox.put((None, time.time_ns(), smp.payload.to_bytes()))))

    def _on_stats(self, sample) -> None:
        self.link_stats = json.loads(sample.payload.to_bytes())

    def drain(self) -> None:
        """Decode what arrived (in this thread, outside the callbacks)."""
        while True:
            try:
                vid, t_ns, payload = self.inbox.get_nowait()
            except queue.Empty:
                return
            header = decode(payload, ObjectList).header
            if vid is None:
                self.published.setdefault(header.seq, header.publish_time_ns)
            else:
                self.received[vid].setdefault(header.seq, t_ns)

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        for session in self.sessions:
            session.close()


# ---- one run ------------------------------------------------------------------------------------

def argv_for(args: argparse.Namespace, kind: str, duration_s: float, **kw) -> list[str]:
    base = [sys.executable, "-m", "v2i"]
    common = ["--scenario", args.scenario, "--await-start", "--duration", str(duration_s)]
    if kind == "rsu":
        return [*base, "rsu", "--listen", kw["ep"], *common, "--rsu-id", RSU_ID, "--clock-offset-ms", "0",
                "--clock-drift-ppm", "0", "--source", "sim"]
    if kind == "obu":
        return [*base, "obu", "--listen", kw["ep"], *common, "--vehicle-id", kw["vid"]]
    if kind == "light":
        return [sys.executable, __file__, "light-vehicle", "--listen", kw["ep"], "--vehicle-id", kw["vid"],
                "--duration", str(duration_s), "--x", str(kw["x"]), "--y", str(kw["y"])]
    vehicles = [a for vid, (ep, tap) in kw["vehicles"].items() for a in ("--vehicle", f"{vid}={ep},{tap}")]
    return [*base, "link", "--config", kw["config"], "--link-id", LINK_ID, "--rsu-connect", kw["ep"],
            "--profile", args.profile, "--seed", "0", *vehicles]


def run_once(args: argparse.Namespace, n_vehicles: int, tmp: Path) -> dict:
    """Start RSU, emulator and ``n_vehicles`` vehicles; measure; stop them; the results."""
    scenario = load_scenario(args.scenario)
    rsu_xy = (scenario.rsu.position.x, scenario.rsu.position.y)
    link_config = tmp / "link.yaml"
    link_config.write_text(json.dumps({"rsu_position": list(rsu_xy), "stats_period_s": 1.0}))
    duration_s = SETTLE_S + args.measure_s + 1.0
    rsu_ep = free_tcp_endpoint()
    vehicles = {f"car{k}": (free_tcp_endpoint(), free_tcp_endpoint()) for k in range(n_vehicles)}
    procs: list[Child] = []
    taps = None
    try:
        procs.append(Child("rsu", argv_for(args, "rsu", duration_s, ep=rsu_ep), label=f"rsu {RSU_ID}"))
        for vid, (ep, _) in vehicles.items():
            procs.append(Child(vid, argv_for(args, args.mode, duration_s, ep=ep, vid=vid,
                                             x=rsu_xy[0] + args.light_distance_m, y=rsu_xy[1])))
        # listening before the emulator connects (a failed connect retries after 1, 2, 4 s)
        ready_s = wait_ready(procs, args.ready_timeout, progress=f"V={n_vehicles}")
        taps = Taps(rsu_ep, {vid: tap for vid, (_, tap) in vehicles.items()})
        procs.append(Child("link", argv_for(args, "link", duration_s, ep=rsu_ep, config=str(link_config),
                                            vehicles=vehicles), label=f"link {LINK_ID}"))
        ready_s += wait_ready(procs[-1:], args.ready_timeout)
        start_ns = start_all(procs)
        window = (start_ns + round(SETTLE_S * 1e9), start_ns + round((SETTLE_S + args.measure_s) * 1e9))
        while time.time_ns() < window[0]:
            time.sleep(0.05)
            taps.drain()
        ticks0 = {p.name: cpu_ticks(p.proc.pid) for p in procs}
        t0 = time.monotonic()
        while time.time_ns() < window[1] + 1_000_000_000:  # lists of the window's end still in flight
            time.sleep(0.05)
            taps.drain()
        elapsed_s = time.monotonic() - t0
        ticks1 = {p.name: cpu_ticks(p.proc.pid) for p in procs}
        rss = {p.name: rss_mb(p.proc.pid) for p in procs}
        taps.drain()
        done = {p.name: done_line(p, 5.0) for p in procs if p.name.startswith("car")} if args.mode == "light" else {}
    finally:
        if taps is not None:
            taps.close()
        for proc in reversed(procs):
            proc.stop()
    cpu = {n: None if ticks1[n] is None or ticks0[n] is None else 100.0 * (ticks1[n] - ticks0[n]) / TICKS_PER_S
           / elapsed_s for n in ticks0}
    expected = {s: t for s, t in taps.published.items() if window[0] <= t < window[1]}
    per_vehicle = {}
    for vid, got in taps.received.items():
        delays = np.array([(got[s] - t) / 1e6 for s, t in expected.items() if s in got])
        per_vehicle[vid] = {"received": len(delays), "expected": len(expected),
                            "p50_ms": float(np.percentile(delays, 50)) if delays.size else None,
                            "p95_ms": float(np.percentile(delays, 95)) if delays.size else None,
                            "cpu_pct": cpu[vid], "rss_mb": rss[vid], "light": done.get(vid)}
    stats = taps.link_stats
    link_stats = {"lateness_ms": stats.get("lateness_ms"), "refused": stats.get("refused"),
                  "relay_delay_ms_mean": [p["downlink"]["delay_ms"]["mean"] for p in stats.get("pairs", [])]}
    return {"vehicles": n_vehicles, "ready_s": round(ready_s, 2), "per_vehicle": per_vehicle, "link_stats": link_stats,
            "rsu": {"cpu_pct": cpu["rsu"], "rss_mb": rss["rsu"]}, "link": {"cpu_pct": cpu["link"], "rss_mb": rss["link"]}}


# ---- report ---------------------------------------------------------------------------------

def delivery_ratio(args: argparse.Namespace) -> float:
    """The profile's declared downlink delivery ratio at the vehicles' distance."""
    distance_m = args.light_distance_m if args.mode == "light" else None
    loss, _, _ = declared_loss(load_profile(args.profile).downlink, Settings(100_000, 0, 200.0, 2000, distance_m))
    return 1.0 - loss


def served(vehicle: dict, ratio: float) -> bool:
    """Received no more than 3 binomial standard deviations below the declared ratio."""
    n = vehicle["expected"]
    return n > 0 and vehicle["received"] >= n * ratio - 3.0 * math.sqrt(n * ratio * (1.0 - ratio))


def _f(value: float | None, spec: str = ".1f") -> str:
    return "-" if value is None else format(value, spec)


def print_table(args: argparse.Namespace, results: list[dict]) -> None:
    ratio = delivery_ratio(args)
    print(f"profile {args.profile} (declared delivery {ratio:.3f}), scenario {args.scenario}, vehicles: {args.mode}, "
          f"{args.measure_s:g} s window, {os.cpu_count()} cores")
    print(f"{'V':>3} {'served':>7} {'recv/exp min':>12} {'mean':>6} {'p50 ms':>7} {'p95 ms':>7} {'worst p95':>9} "
          f"{'link CPU%':>9} {'link MB':>7} {'rsu CPU%':>8} {'veh CPU% mean':>13} {'veh MB mean':>11}")
    for r in results:
        vs = list(r["per_vehicle"].values())
        ratios = [v["received"] / v["expected"] for v in vs if v["expected"]]
        p50s = [v["p50_ms"] for v in vs if v["p50_ms"] is not None]
        p95s = [v["p95_ms"] for v in vs if v["p95_ms"] is not None]
        ok = sum(served(v, ratio) for v in vs)
        worst = min(vs, key=lambda v: v["received"] / max(v["expected"], 1))
        print(f"{r['vehicles']:>3} {ok:>3}/{len(vs):<3} {worst['received']:>5}/{worst['expected']:<6} "
              f"{np.mean(ratios) if ratios else 0:>6.3f} {_f(np.median(p50s) if p50s else None):>7} "
              f"{_f(np.median(p95s) if p95s else None):>7} {_f(max(p95s) if p95s else None):>9} "
              f"{_f(r['link']['cpu_pct']):>9} {_f(r['link']['rss_mb'], '.0f'):>7} {_f(r['rsu']['cpu_pct']):>8} "
              f"{_f(np.mean([v['cpu_pct'] or 0 for v in vs])):>13} {_f(np.mean([v['rss_mb'] or 0 for v in vs]), '.0f'):>11}")
    for r in results:
        s = r["link_stats"]
        means = [m for m in s["relay_delay_ms_mean"] if m is not None]
        print(f"V={r['vehicles']}: every process ready after {r['ready_s']:.1f} s; emulator lateness {s['lateness_ms']}, refused {s['refused']}, relay delay mean "
              f"per pair {_f(min(means) if means else None)}-{_f(max(means) if means else None)} ms "
              f"(whole run, lists and time replies)")
    if args.per_vehicle:
        for r in results:
            print(f"V={r['vehicles']}: " + "; ".join(
                f"{vid} {v['received']}/{v['expected']} p50 {_f(v['p50_ms'])} p95 {_f(v['p95_ms'])} ms "
                f"CPU {_f(v['cpu_pct'])}% {_f(v['rss_mb'], '.0f')} MB{_light(v['light'])}"
                for vid, v in r["per_vehicle"].items()))


def _light(done: dict | None) -> str:
    """A light vehicle's own counts: time replies / queries over its whole run, lists decoded."""
    if not done:
        return ""
    return f" (time replies {done['time_replies']}/{done['time_queries']}, lists decoded {done['received']})"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command")
    light = sub.add_parser("light-vehicle", help="(internal) one light vehicle process")
    light.add_argument("--listen", required=True)
    light.add_argument("--vehicle-id", required=True)
    light.add_argument("--duration", type=float, required=True)
    light.add_argument("--x", type=float, default=0.0)
    light.add_argument("--y", type=float, default=0.0)
    parser.add_argument("--vehicles", type=int, nargs="+", default=[1, 5, 10, 20], help="V values (default 1 5 10 20)")
    parser.add_argument("--mode", choices=("obu", "light"), default="obu", help="vehicle processes (default obu)")
    parser.add_argument("--scenario", default="red-light-runner")
    parser.add_argument("--profile", default="lte-v2x")
    parser.add_argument("--measure-s", type=float, default=10.0, help="measurement window, s (default 10)")
    parser.add_argument("--light-distance-m", type=float, default=50.0, help="light vehicles' distance to the RSU")
    parser.add_argument("--per-vehicle", action="store_true", help="also print one line per vehicle")
    parser.add_argument("--ready-timeout", type=float, default=READY_TIMEOUT_S,
                        help="s every process may take to be ready (default %(default)s); the scenario starts when all are")
    parser.add_argument("--json", metavar="PATH", help="write the results as JSON")
    args = parser.parse_args(argv)
    if args.command == "light-vehicle":
        return light_vehicle(args)
    import tempfile
    results = []
    for n in args.vehicles:
        with tempfile.TemporaryDirectory(prefix="v2i-scale-vehicles-") as tmp:
            results.append(run_once(args, n, Path(tmp)))
        print(f"V={n} done", file=sys.stderr, flush=True)
    print_table(args, results)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
