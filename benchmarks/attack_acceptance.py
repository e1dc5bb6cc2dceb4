"""Issue 14's acceptance run: ``v2i attack`` against a live ``v2i demo`` and the numbers it prints.

1. A site PKI in a temporary directory with the attacker's material made by the lab first
   (``prepare_attacker_pki``: stolen ``rsu-evil`` and ``stolen-vehicle`` keys, the revoked
   ``rsu1-revoked`` key covering rsu1's keys), before any service loads the trust directory.
2. ``v2i demo --security POLICY --pki DIR`` (red-light-runner, lte-v2x) long enough for the attack;
   the endpoints are read from its log line.
3. ``v2i attack --count N`` of every kind (unsigned, forged, replayed, wrong_key, revoked, time,
   control) against the OBU, sniffing the RSU, with the emulator's control endpoint.
4. The attack's table and the demo's own summary (output and RSU deadline misses, refusals).

    python benchmarks/attack_acceptance.py                      # strict, 1000 per kind (~5 min)
    python benchmarks/attack_acceptance.py --security permissive --count 1000
    python benchmarks/attack_acceptance.py --count 100 --json /tmp/attack.json
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from v2i.adversary.attack_messages import KINDS
from v2i.security.attacker_keys import prepare_attacker_pki

ENDPOINTS = re.compile(r"endpoints: OBU (\S+), RSU (\S+), link (\S+)")
READY_S = 60.0


def attack_seconds(count: int, rate_hz: float, time_burst: int, settle_s: float = 1.5) -> float:
    """How long the attack takes: every kind at ``rate_hz`` (time: 10 queries/s x burst), each settled."""
    list_like = len(KINDS) - 1  # all but time are paced at rate_hz
    return 10.0 + list_like * (count / rate_hz + settle_s + 1.0) + count / (10.0 * time_burst) + settle_s + 1.0


def start_demo(pki: Path, security: str, duration_s: float, json_path: Path) -> tuple[subprocess.Popen, list[str]]:
    """The demo as a child process, and its stderr lines as they come (a reader thread)."""
    argv = [sys.executable, "-m", "v2i", "demo", "--security", security, "--pki", str(pki), "--duration",
            f"{duration_s:.0f}", "--quiet", "--json", str(json_path)]
    demo = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(iter(demo.stderr.readline, "")), daemon=True).start()
    return demo, lines


def endpoints(demo: subprocess.Popen, lines: list[str]) -> tuple[str, str, str]:
    deadline = time.monotonic() + READY_S
    while time.monotonic() < deadline and demo.poll() is None:
        for line in list(lines):
            if m := ENDPOINTS.search(line):
                return m.groups()
        time.sleep(0.1)
    raise SystemExit(f"the demo logged no endpoints within {READY_S:g} s:\n{''.join(lines[-20:])}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--security", default="strict", choices=("strict", "permissive"))
    p.add_argument("--count", type=int, default=1000)
    p.add_argument("--rate-hz", type=float, default=30.0)
    p.add_argument("--time-burst", type=int, default=3)
    p.add_argument("--json", metavar="PATH", help="also write the attack report JSON here")
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="v2i-attack-") as tmp:
        pki, attack_json, demo_json = Path(tmp) / "pki", Path(tmp) / "attack.json", Path(tmp) / "demo.json"
        prepare_attacker_pki(pki, time.time_ns(), "rsu1")
        duration_s = attack_seconds(args.count, args.rate_hz, args.time_burst) * 1.2 + 20.0
        print(f"demo --security {args.security}, {duration_s:.0f} s; attack {args.count} per kind at {args.rate_hz:g}/s",
              flush=True)
        demo, lines = start_demo(pki, args.security, duration_s, demo_json)
        try:
            obu, rsu, link = endpoints(demo, lines)
            attack = subprocess.run([sys.executable, "-m", "v2i", "attack", "--connect", obu, "--sniff", rsu,
                                     "--control", link, "--pki", str(pki), "--count", str(args.count), "--rate-hz",
                                     str(args.rate_hz), "--time-burst", str(args.time_burst), "--json",
                                     str(attack_json)], check=False)
            out, _ = demo.communicate(timeout=duration_s + 60.0)
        finally:
            if demo.poll() is None:
                demo.terminate()
                demo.wait(10)
        print(f"v2i attack exit code {attack.returncode} (0: nothing got through)")
        print("demo:", *[line for line in out.splitlines() if "deadline misses" in line or "first seen" in line], sep="\n  ")
        print("demo " + next((line.strip() for line in lines if "[obu] stopped" in line), "(no OBU summary)"))
        if args.json and attack_json.exists():
            report = json.loads(attack_json.read_text())
            report["demo"] = json.loads(demo_json.read_text()) if demo_json.exists() else None
            Path(args.json).write_text(json.dumps(report, indent=2) + "\n")
        return attack.returncode


if __name__ == "__main__":
    sys.exit(main())
