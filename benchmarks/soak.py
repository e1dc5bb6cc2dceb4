"""Soak test of the live demo: does any process's memory grow over a long run?

    python benchmarks/soak.py                      # 30 min, fail on > 10 MB growth after 60 s
    python benchmarks/soak.py --minutes 5 --max-growth-mb 10 --warmup-s 60 -- --profile dsrc

Starts ``python -m v2i demo --duration <minutes * 60> --json <tmp>`` (arguments after ``--``
go to the demo), finds its children (RSU, OBU, link emulator) in /proc by parent pid, and
samples the resident set size (VmRSS in /proc/<pid>/status) of the orchestrator and of each
child every ``--interval-s``, and the orchestrator's alone while it builds its report after the
services stopped. Prints a table (start, end of warm-up, every ``--table-every-min``, end of the
services, report), per process the growth after warm-up (peak and last sample minus the sample
at the end of warm-up) and a least-squares slope, then the demo's own summary line.

Growth is measured after ``--warmup-s`` (default 60 s: start-up, imports, Zenoh sessions, the
scenario's 30 s of moving actors and first allocations of every code path). After the
scenario's end the actors stay where their paths end (static world), and the services keep
running their 10 Hz cycles, RSU lists, clock sync and relaying for the whole duration.

Exit code: 0 when every process stayed within ``--max-growth-mb`` (peak after warm-up), 1 when
one grew more, 2 when the demo failed or a process could not be sampled.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SERVICES = ("rsu", "obu", "link")
PROCESSES = ("demo",) + SERVICES


def rss_mb(pid: int) -> float | None:
    """Resident set size of ``pid`` (MB = 2^20 bytes); None once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0  # kB
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def children_of(parent_pid: int) -> dict[str, int]:
    """{service: pid} of the ``python -m v2i <service>`` processes whose parent is ``parent_pid``."""
    found = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()  # after "(comm)": state, ppid, ...
            if int(fields[1]) != parent_pid:
                continue
            argv = (stat.parent / "cmdline").read_bytes().split(b"\0")
        except (FileNotFoundError, ProcessLookupError, IndexError, ValueError):
            continue
        for service in SERVICES:
            if [b"-m", b"v2i", service.encode()] in (argv[i:i + 3] for i in range(len(argv))):
                found[service] = int(stat.parent.name)
    return found


def sample_loop(demo: subprocess.Popen, interval_s: float) -> list[tuple[float, dict[str, float]]]:
    """[(elapsed s, {process: RSS MB})] every ``interval_s`` until the demo exits, from the first
    sample with every service; a process that has exited is missing from its samples (the
    orchestrator scoring the run after the services stopped)."""
    samples, pids, t0 = [], {"demo": demo.pid}, time.monotonic()
    while demo.poll() is None:
        for service, pid in children_of(demo.pid).items():
            if pids.get(service) not in (None, pid):
                print(f"soak: {service} has a new pid {pid} (restarted)", file=sys.stderr)
            pids[service] = pid
        rss = {name: mb for name, pid in pids.items() if (mb := rss_mb(pid)) is not None}
        if samples or set(PROCESSES) <= set(rss):
            samples.append((time.monotonic() - t0, rss))
        time.sleep(interval_s)
    return samples


def growth(samples: list[tuple[float, dict[str, float]]], warmup_s: float) -> dict[str, dict[str, float]]:
    """Per process, after warm-up: baseline (first sample at or after warmup_s), peak - baseline,
    last - baseline (MB) and the least-squares slope (MB/min) of RSS against time."""
    out = {}
    for name in PROCESSES:
        after = [(t, rss[name]) for t, rss in samples if t >= warmup_s and name in rss]
        t, mb = np.array([a[0] for a in after]) / 60.0, np.array([a[1] for a in after])
        slope = float(np.polyfit(t, mb, 1)[0]) if len(t) >= 2 else float("nan")
        out[name] = {"baseline_mb": mb[0], "peak_growth_mb": mb.max() - mb[0], "end_growth_mb": mb[-1] - mb[0],
                     "slope_mb_per_min": slope}
    return out


def table(samples: list[tuple[float, dict[str, float]]], warmup_s: float, every_min: float) -> str:
    """RSS (MB) per process at the first sample, the end of warm-up, every ``every_min`` and the end."""
    services_end = max(t for t, rss in samples if set(PROCESSES) <= set(rss))
    marks = [0.0, warmup_s] + list(np.arange(every_min * 60.0, services_end, every_min * 60.0))
    marks += [services_end, samples[-1][0]]
    rows, used = [], set()
    for mark in sorted(set(marks)):
        i = next((k for k, (t, _) in enumerate(samples) if t >= mark), len(samples) - 1)
        if i in used:
            continue
        used.add(i)
        t, rss = samples[i]
        label = {0.0: "start", warmup_s: "warm-up end", services_end: "services end"}.get(mark, "")
        label = "report" if i == len(samples) - 1 and set(rss) != set(PROCESSES) else label
        rows.append(f"{t / 60.0:8.2f} {label:>12} " + " ".join(f"{rss[n]:9.1f}" if n in rss else f"{'-':>9}"
                                                            for n in PROCESSES))
    head = f"{'min':>8} {'':>12} " + " ".join(f"{n + ' MB':>9}" for n in PROCESSES)
    return "\n".join([head, *rows])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=30.0, help="length of the live demo (default 30)")
    p.add_argument("--max-growth-mb", type=float, default=10.0, help="allowed RSS growth after warm-up (default 10)")
    p.add_argument("--warmup-s", type=float, default=60.0, help="growth is measured from this time on (default 60)")
    p.add_argument("--interval-s", type=float, default=5.0, help="sampling period (default 5)")
    p.add_argument("--table-every-min", type=float, default=5.0, help="table row spacing (default 5)")
    p.add_argument("--csv", help="write every sample here (elapsed_s and RSS MB per process)")
    p.add_argument("demo_args", nargs="*", help="after --: more `v2i demo` options (e.g. --scenario, --profile)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="v2i-soak-") as tmp:
        report_path = Path(tmp) / "report.json"
        cmd = [sys.executable, "-m", "v2i", "demo", "--duration", str(args.minutes * 60.0), "--json", str(report_path),
               *args.demo_args]
        print("soak: " + " ".join(cmd[1:]), file=sys.stderr)
        demo = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
        try:
            samples = sample_loop(demo, args.interval_s)
        finally:
            if demo.poll() is None:
                demo.send_signal(2)  # SIGINT: the demo stops its services
                demo.wait()
        if demo.returncode != 0 or not report_path.exists():
            print(f"soak: the demo failed (exit code {demo.returncode})", file=sys.stderr)
            return 2
        report = json.loads(report_path.read_text())
    if not samples or samples[-1][0] < args.warmup_s:
        print("soak: no samples after the warm-up", file=sys.stderr)
        return 2
    if args.csv:
        Path(args.csv).write_text("elapsed_s," + ",".join(f"{n}_mb" for n in PROCESSES) + "\n" + "".join(
            f"{t:.1f}," + ",".join(f"{rss[n]:.2f}" if n in rss else "" for n in PROCESSES) + "\n" for t, rss in samples))
    print(table(samples, args.warmup_s, args.table_every_min))
    grown = growth(samples, args.warmup_s)
    print(f"growth after {args.warmup_s:g} s of warm-up ({len(samples)} samples every {args.interval_s:g} s; "
          f"the orchestrator's include its scoring after the services stopped):")
    for name, g in grown.items():
        print(f"  {name:5s} baseline {g['baseline_mb']:7.1f} MB  peak {g['peak_growth_mb']:+6.1f} MB  "
              f"end {g['end_growth_mb']:+6.1f} MB  slope {g['slope_mb_per_min']:+.3f} MB/min")
    print(f"demo: {report['outputs']}/{report['cycles']} cycles published, output deadline misses "
          f"{report['output_deadline_miss_ratio']:.1%}, RSU lists {report['rsu_messages_received']}, "
          f"modes {report['mode_share']}, scorer drops {report.get('monitor_messages_dropped')}")
    worst = max(grown, key=lambda n: grown[n]["peak_growth_mb"])
    if grown[worst]["peak_growth_mb"] > args.max_growth_mb:
        print(f"soak: FAIL: {worst} grew {grown[worst]['peak_growth_mb']:.1f} MB > {args.max_growth_mb:g} MB "
              f"after warm-up", file=sys.stderr)
        return 1
    print(f"soak: OK: every process within {args.max_growth_mb:g} MB after warm-up", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
