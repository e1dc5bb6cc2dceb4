"""CLI start-up: ``v2i --help``, ``v2i eval --help`` and the time until a service is ready.

    python benchmarks/cli_start.py [--runs 5] [--scenario red-light-runner]

Each command runs as its own process (``python -m v2i ...``, as the services are started by
``v2i demo``); the median and the spread of ``--runs`` runs are printed, in seconds.
Ready = the service's ``{"event": "ready", ...}`` line on stdout (``v2i.runtime.process``: printed
once its Zenoh session is open and declared; the link emulator prints it once both sides are
open). Per run: the RSU and the OBU start (each on a free loopback port), then the link
emulator connecting the two; each is timed from its spawn to its ready line; then all three
are stopped with SIGINT. ``--importtime`` adds, per command, the modules with the largest
cumulative import time (``python -X importtime``).

Imports are ~0.2 s of a service's start-up more when Python may not cache their bytecode
(``PYTHONDONTWRITEBYTECODE`` set, as in some sandboxes and CI images; a normal install caches it
at the first import): the first line printed says which of the two was measured.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import time

READY_TIMEOUT_S = 30.0


def free_endpoint() -> str:
    """A loopback TCP endpoint on a port free now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{sock.getsockname()[1]}"


def v2i(*args: str) -> list[str]:
    return [sys.executable, "-m", "v2i", *args]


def time_exit(argv: list[str]) -> float:
    """Wall seconds of a command that exits by itself (exit code 0 required)."""
    start = time.perf_counter()
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def start_until_ready(argv: list[str]) -> tuple[subprocess.Popen, float]:
    """Spawn a service; return it and the seconds until it printed its ready line."""
    start = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    for line in proc.stdout:
        if line.startswith("{") and json.loads(line).get("event") == "ready":
            return proc, time.perf_counter() - start
        if time.perf_counter() - start > READY_TIMEOUT_S:
            break
    proc.kill()
    raise RuntimeError(f"{' '.join(argv[2:])}: no ready line (exit code {proc.wait()})")


def stop(procs: list[subprocess.Popen]) -> None:
    for proc in procs:
        proc.send_signal(signal.SIGINT)
    for proc in procs:
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def service_run(scenario: str) -> dict[str, float]:
    """One start of RSU, OBU and link emulator: seconds from spawn to ready, per service."""
    rsu_ep, obu_ep = free_endpoint(), free_endpoint()
    procs, ready = [], {}
    try:
        for name, argv in (("rsu", v2i("rsu", "--listen", rsu_ep, "--scenario", scenario)),
                           ("obu", v2i("obu", "--listen", obu_ep, "--scenario", scenario)),
                           ("link", v2i("link", "--rsu-connect", rsu_ep, "--vehicle-connect", obu_ep))):
            proc, ready[name] = start_until_ready(argv)
            procs.append(proc)
    finally:
        stop(procs)
    return ready


def import_top(argv: list[str], top: int) -> list[str]:
    """The ``top`` modules by cumulative import time of a command that exits by itself."""
    err = subprocess.run([sys.executable, "-X", "importtime", *argv[1:]], check=False, capture_output=True, text=True).stderr
    rows = []
    for line in err.splitlines():
        parts = line.split("|")
        if len(parts) == 3 and parts[1].strip().isdigit():
            rows.append((int(parts[1]), parts[2].rstrip()))
    return [f"{us / 1000:8.1f} ms {name}" for us, name in sorted(rows, reverse=True)[:top]]


def summary(label: str, seconds: list[float]) -> str:
    return f"{label:20s} median {statistics.median(seconds):6.3f} s  min {min(seconds):6.3f}  max {max(seconds):6.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=5, help="runs per command (default %(default)s)")
    parser.add_argument("--scenario", default="red-light-runner", help="the services' scenario (default %(default)s)")
    parser.add_argument("--importtime", type=int, metavar="N", help="print each --help command's N costliest imports")
    args = parser.parse_args()
    print("bytecode cache: " + ("off (PYTHONDONTWRITEBYTECODE is set: every import compiles from source)"
                                if os.environ.get("PYTHONDONTWRITEBYTECODE") else "on"), flush=True)
    helps = {"v2i --help": v2i("--help"), "v2i eval --help": v2i("eval", "--help")}
    for label, argv in helps.items():
        print(summary(label, [time_exit(argv) for _ in range(args.runs)]), flush=True)
        for row in import_top(argv, args.importtime) if args.importtime else ():
            print("    " + row)
    runs = [service_run(args.scenario) for _ in range(args.runs)]
    for name in ("rsu", "obu", "link"):
        print(summary(f"v2i {name} ready", [r[name] for r in runs]), flush=True)


if __name__ == "__main__":
    main()
