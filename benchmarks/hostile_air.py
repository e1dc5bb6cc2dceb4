"""Issue 32's acceptance ("hostile air") as one script: a strict site on plain ``tcp/`` loopback
endpoints, the README's "Running on two hosts" recipe, and a keyless attacker's runs against it.

The site: ``v2i pki site DIR --rsu rsu1 --vehicle ego``, then ``v2i pki attacker DIR --rsu-id rsu1``
(the stolen keys ``v2i attack`` loads; none of them covers the genuine RSU's keys);
``v2i rsu --listen EP --await-start --pki DIR`` with its clock 350 ms ahead and drifting 60 ppm,
``v2i obu --listen EP --await-start --pki DIR`` (``--known-rsus rsu1`` when the OBU has that
option), ``v2i link --profile lte-v2x --pki DIR`` between them, on free ports; the start line is sent
once every one printed ready (``v2i.orchestration.children``). Each run prints one line of numbers:

- ``flood``: ``v2i attack --kinds flood`` at each of ``--rates`` (100, 500, 2000 msg/s) for
  ``--flood-s`` (20 s) on one site: genuine lists accepted of sent, ghosts, output misses, cycles by
  mode, the load reached;
- ``time_doubled``: on a fresh site, ``v2i attack --kinds time_doubled --from-start`` started before
  the start line, for ``--doubled-s`` (40 s): time zero to the OBU's first clock estimate, the share
  of intra / inter cycles, both beside a fresh site's run without any attack (``baseline``);
- ``time_delayed``: ``v2i attack --kinds time_delayed --time-delay-ms 100`` for ``--delayed-s``
  (30 s): steps confirmed, and the OBU's offset against the RSU clock's truth
  (350 ms + 60 ppm x (t - time zero)) beside the uncertainty it states;
- ``trickle`` (``--trickle``): 300 raw TCP connections to the OBU's endpoint, one byte every 2 s
  each, for ``--flood-s`` (``v2i.adversary.trickle``), with the genuine lists accepted of sent.

    python benchmarks/hostile_air.py                              # flood, doubled, delayed (~6 min)
    python benchmarks/hostile_air.py --only flood --rates 100 --json /tmp/hostile.json
    python benchmarks/hostile_air.py --trickle

Every process started here is stopped by its pid; every session is closed.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from schemas import keys
from schemas.codec import decode
from schemas.messages import ObuMetrics
from v2i.adversary.attack_report import counter_delta, genuine_sent_in, tracking_share
from v2i.orchestration.children import Child, start_all, wait_ready
from v2i.runtime.transport import free_tcp_endpoint, open_session

RSU_ID, VEHICLE_ID = "rsu1", "ego"
RSU_OFFSET_MS, RSU_DRIFT_PPM = 350.0, 60.0
SITE_S = 900.0  # the services' --duration: longer than any run; they are stopped when it is done
RUNS = ("flood", "time_doubled", "time_delayed", "trickle")
TRICKLE_CONNECTIONS, TRICKLE_BYTE_INTERVAL_S = 300, 2.0
V2I = [sys.executable, "-m", "v2i"]


def truth_offset_ns(t_ns: int, start_ns: int) -> float:
    """The RSU clock's lead over the true (OBU) clock at ``t_ns``: 350 ms + 60 ppm (t - time zero)."""
    return RSU_OFFSET_MS * 1e6 + RSU_DRIFT_PPM * 1e-6 * (t_ns - start_ns)


def make_pki(folder: Path) -> Path:
    pki = folder / "pki"
    for argv in (["pki", "site", str(pki), "--rsu", RSU_ID, "--vehicle", VEHICLE_ID],
                 ["pki", "attacker", str(pki), "--rsu-id", RSU_ID]):
        subprocess.run(V2I + argv, check=True, capture_output=True, text=True)
    return pki


def _obu_knows_rsus_option() -> bool:
    """Whether ``v2i obu`` takes ``--known-rsus`` (issue 32 item 5): then the OBU is told its RSU."""
    text = subprocess.run(V2I + ["obu", "--help"], capture_output=True, text=True, check=False).stdout
    return "--known-rsus" in text


class Site:
    """RSU, OBU and link emulator of the README's recipe on loopback; ``start`` sends the start line."""

    def __init__(self, pki: Path, known_rsus: bool):
        self.rsu_ep, self.obu_ep = free_tcp_endpoint(), free_tcp_endpoint()
        common = ["--await-start", "--pki", str(pki), "--duration", f"{SITE_S:g}"]
        obu_extra = ["--known-rsus", RSU_ID] if known_rsus else []
        self.children = [
            Child("rsu", V2I + ["rsu", "--listen", self.rsu_ep, *common, "--rsu-id", RSU_ID, "--clock-offset-ms",
                                f"{RSU_OFFSET_MS:g}", "--clock-drift-ppm", f"{RSU_DRIFT_PPM:g}"]),
            Child("obu", V2I + ["obu", "--listen", self.obu_ep, *common, "--vehicle-id", VEHICLE_ID, *obu_extra]),
            Child("link", V2I + ["link", "--rsu-connect", self.rsu_ep, "--vehicle-connect", self.obu_ep, "--profile",
                                 "lte-v2x", "--pki", str(pki), "--duration", f"{SITE_S:g}"]),
        ]
        self.start_ns: int | None = None

    def ready(self) -> None:
        wait_ready(self.children)

    def start(self) -> int:
        self.start_ns = start_all(self.children)
        return self.start_ns

    def stop(self) -> None:
        for child in self.children:
            child.stop()

    def check_alive(self) -> list[str]:
        return [f"{c.name} exited with {c.proc.returncode}" for c in self.children if c.proc.poll() is not None]


def attack_argv(site: Site, pki: Path, report: Path, *options: str) -> list[str]:
    return V2I + ["attack", "--connect", site.obu_ep, "--sniff", site.rsu_ep, "--pki", str(pki), "--rsu-id", RSU_ID,
                  "--vehicle-id", VEHICLE_ID, "--warmup-s", "1", "--settle-s", "1.5", "--json", str(report), *options]


def run_attack(argv: list[str], report: Path, timeout_s: float) -> dict:
    """``v2i attack`` to its end; its report (``{}`` and its stderr's tail when it wrote none)."""
    result = subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s, check=False)
    if not report.exists():
        print(f"  v2i attack wrote no report (exit {result.returncode}): {result.stderr[-1500:]}", flush=True)
        return {}
    return json.loads(report.read_text())


class Watch:
    """The site as a bystander sees it: genuine lists sniffed at the RSU, OBU metrics (for the runs
    ``v2i attack`` does not make: the baseline and the trickle)."""

    def __init__(self, site: Site):
        self.sniffed: list[int] = []
        self.metrics: list[ObuMetrics] = []
        self._lock = threading.Lock()
        self._sessions = [open_session(connect=[site.rsu_ep]), open_session(connect=[site.obu_ep])]
        self._subs = [self._sessions[0].declare_subscriber(keys.rsu_objects(RSU_ID), self._on_list),
                      self._sessions[1].declare_subscriber(keys.obu_metrics(VEHICLE_ID), self._on_metrics)]

    def _on_list(self, sample) -> None:
        with self._lock:
            self.sniffed.append(time.time_ns())

    def _on_metrics(self, sample) -> None:
        metrics = decode(sample.payload.to_bytes(), ObuMetrics)
        with self._lock:
            self.metrics.append(metrics)

    def latest(self) -> ObuMetrics | None:
        with self._lock:
            return self.metrics[-1] if self.metrics else None

    def wait_metrics(self, after_ns: int, timeout_s: float = 10.0) -> ObuMetrics | None:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if (m := self.latest()) is not None and m.t_ns >= after_ns:
                return m
            time.sleep(0.02)
        return self.latest()

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        for session in self._sessions:
            session.close()


def _status(m: ObuMetrics | None):
    return next((r for r in m.rsus if r.rsu_id == RSU_ID), None) if m else None


def window_numbers(watch: Watch, m0: ObuMetrics | None, m1: ObuMetrics) -> dict:
    """Genuine lists accepted of sent, cycles by mode, misses, between two OBU metrics (m0 None: from the start)."""
    s0, s1 = _status(m0), _status(m1)
    delay_ns = round(((s1.delay_p50_ms if s1 else None) or 0.0) * 1e6)
    t0 = m0.t_ns if m0 else 0
    with watch._lock:
        sniffed = sorted(watch.sniffed)
        window = [m for m in watch.metrics if t0 <= m.t_ns <= m1.t_ns]
    synced = next((m.t_ns for m in window if (s := _status(m)) and s.clock_offset_ns is not None), None)
    modes = counter_delta(m1.mode_counts, m0.mode_counts if m0 else {})
    return {"genuine_sent": genuine_sent_in(sniffed, t0, m1.t_ns, delay_ns),
            "genuine_accepted": (s1.messages_accepted if s1 else 0) - (s0.messages_accepted if s0 else 0),
            "modes": modes, "tracking_share": tracking_share(modes), "first_sync_ns": synced,
            "output_deadline_misses": m1.output_deadline_misses - (m0.output_deadline_misses if m0 else 0),
            "cycles": m1.cycles - (m0.cycles if m0 else 0), "clock_steps": s1.clock_steps if s1 else 0}


# --- the runs -------------------------------------------------------------------------------------------
def run_baseline(pki: Path, known: bool, seconds: float) -> dict:
    """A fresh site, no attack, ``seconds`` from time zero: the numbers the doubled replies are compared with."""
    site = Site(pki, known)
    try:
        site.ready()
        watch = Watch(site)
        try:
            start_ns = site.start()
            time.sleep(seconds + 1.5)
            m1 = watch.wait_metrics(start_ns + round(seconds * 1e9))
            numbers = window_numbers(watch, None, m1)
        finally:
            watch.close()
    finally:
        site.stop()
    synced = numbers["first_sync_ns"]
    numbers["first_sync_s"] = None if synced is None else round((synced - start_ns) / 1e9, 2)
    return numbers


def run_doubled(pki: Path, known: bool, seconds: float, folder: Path) -> dict:
    """A fresh site; the relay doubling genuine replies from before the OBU's first query."""
    site, report = Site(pki, known), folder / "doubled.json"
    attack = None
    try:
        site.ready()
        attack = Child("attack", attack_argv(site, pki, report, "--kinds", "time_doubled", "--from-start",
                                             "--time-s", f"{seconds:g}"))
        wait_ready([attack])  # its sessions are open, its queryable declared: the OBU's first query meets it
        start_ns = site.start()
        attack.proc.wait(timeout=seconds + 180.0)
        alive = site.check_alive()
    finally:
        if attack is not None:
            attack.stop()
        site.stop()
    row = json.loads(report.read_text())["kinds"]["time_doubled"] if report.exists() else {}
    if row:
        row["first_sync_from_zero_s"] = _sync_from_zero(row, start_ns)
    return {"row": row, "start_ns": start_ns, "dead": alive}


def _sync_from_zero(row: dict, start_ns: int) -> float | None:
    samples = row.get("clock_samples") or []
    return None if not samples else round((samples[0][0] - start_ns) / 1e9, 2)


def run_on_one_site(pki: Path, known: bool, args, runs: list[str], folder: Path) -> dict:
    """Floods at each rate, the delayed request legs and the trickle, one after another on one site."""
    site, out = Site(pki, known), {}
    try:
        site.ready()
        start_ns = site.start()
        if "flood" in runs:
            out["flood"] = []
            for rate in args.rates:
                report = folder / f"flood-{rate:g}.json"
                data = run_attack(attack_argv(site, pki, report, "--kinds", "flood", "--flood-rate-hz", f"{rate:g}",
                                              "--flood-s", f"{args.flood_s:g}"), report, args.flood_s + 240.0)
                out["flood"].append(data.get("kinds", {}).get("flood", {}))
                print_flood(rate, out["flood"][-1])
        if "time_delayed" in runs:
            report = folder / "delayed.json"
            data = run_attack(attack_argv(site, pki, report, "--kinds", "time_delayed", "--time-s",
                                          f"{args.delayed_s:g}", "--time-delay-ms", f"{args.delay_ms:g}"),
                              report, args.delayed_s + 240.0)
            out["time_delayed"] = data.get("kinds", {}).get("time_delayed", {})
            print_delayed(out["time_delayed"], start_ns)
        if "trickle" in runs:
            out["trickle"] = run_trickle(site, args.flood_s)
            print_trickle(out["trickle"])
        out["dead"] = site.check_alive()
    finally:
        site.stop()
    return out


def run_trickle(site: Site, seconds: float) -> dict:
    """300 raw connections to the OBU's endpoint, one byte each every 2 s, while the genuine lists are counted."""
    try:
        from v2i.adversary.trickle import TrickleSpec, parse_endpoint
        from v2i.adversary.trickle import run_trickle as trickle
    except ImportError:
        return {"skipped": "v2i.adversary.trickle is not there"}
    watch = Watch(site)  # connected before the trickle holds the OBU's accept slots
    try:
        m0 = watch.wait_metrics(time.time_ns())
        host, port = parse_endpoint(site.obu_ep)
        counts = trickle(host, port, TrickleSpec(TRICKLE_CONNECTIONS, TRICKLE_BYTE_INTERVAL_S, seconds))
        m1 = watch.wait_metrics(time.time_ns() + 200_000_000)
        numbers = window_numbers(watch, m0, m1)
    finally:
        watch.close()
    numbers["trickle"] = counts.as_dict()
    return numbers


# --- the lines ------------------------------------------------------------------------------------------
def _modes(modes: dict) -> str:
    return ", ".join(f"{m} {n}" for m, n in sorted(modes.items())) or "-"


def print_flood(rate: float, row: dict) -> None:
    if not row:
        print(f"flood {rate:g}/s: no report", flush=True)
        return
    print(f"flood {rate:g}/s for {row['send_s']:g} s: load {row['achieved_hz']:g} msg/s ({_modes(row['variants'])}); "
          f"genuine accepted {row['genuine_accepted']} of {row['genuine_sent']}; ghosts {row['ghost_outputs']} in "
          f"{row['outputs']} outputs; output misses {row['output_deadline_misses']} of {row['cycles']} cycles; "
          f"modes {_modes(row['modes'])}, crowded out {row['crowded_out_cycles']}; verifier refused "
          f"{_modes(row['rejected'])}; intake refused {_modes(row['other_refusals'])}", flush=True)


def print_doubled(doubled: dict, baseline: dict | None) -> None:
    row = doubled["row"]
    if not row:
        print("time_doubled: no report", flush=True)
        return
    share = row["tracking_share"]
    line = (f"time_doubled {row['window_s']:g} s from the OBU's start: first clock estimate "
            f"{row.get('first_sync_from_zero_s')} s after time zero; intra or inter "
            f"{'-' if share is None else f'{100 * share:.1f} %'} of {row['cycles']} cycles ({_modes(row['modes'])}); "
            f"samples {row['sync_samples']}, steps {row['clock_steps']}; output misses {row['output_deadline_misses']}; "
            f"relay {_modes(row['relay'])}; refused {_modes(row['rejected'])}")
    if baseline:
        base_share = baseline["tracking_share"]
        line += (f" | without attack: first estimate {baseline['first_sync_s']} s after time zero; intra or inter "
                 f"{'-' if base_share is None else f'{100 * base_share:.1f} %'} of {baseline['cycles']} cycles; "
                 f"genuine lists accepted {baseline['genuine_accepted']} of {baseline['genuine_sent']}; steps "
                 f"{baseline['clock_steps']}")
    print(line, flush=True)


def offset_errors(row: dict, start_ns: int) -> list[tuple[float, float]]:
    """(|offset - truth| ms, stated uncertainty ms) per clock sample of a relay row."""
    return [(abs(offset - truth_offset_ns(t, start_ns)) / 1e6, unc / 1e6) for t, offset, unc in row["clock_samples"]]


def print_delayed(row: dict, start_ns: int) -> None:
    if not row:
        print("time_delayed: no report", flush=True)
        return
    errors = offset_errors(row, start_ns)
    within = sum(1 for e, u in errors if e <= u)
    worst = max(errors, default=(float("nan"), float("nan")))
    share = row["tracking_share"]
    print(f"time_delayed {row['delay_ms']:g} ms for {row['window_s']:g} s: steps confirmed {row['clock_steps']}; "
          f"offset error vs truth within the stated uncertainty in {within} of {len(errors)} samples (worst "
          f"{worst[0]:.2f} ms, stated {worst[1]:.2f} ms; last offset {row['offset_ms']} ms +- {row['uncertainty_ms']}); "
          f"samples +{row['sync_samples']}; intra or inter {'-' if share is None else f'{100 * share:.1f} %'}; "
          f"relay {_modes(row['relay'])}; refused {_modes(row['rejected'])}", flush=True)


def print_trickle(numbers: dict) -> None:
    if "skipped" in numbers:
        print(f"trickle: skipped ({numbers['skipped']})", flush=True)
        return
    t = numbers["trickle"]
    print(f"trickle {TRICKLE_CONNECTIONS} connections: genuine accepted {numbers['genuine_accepted']} of "
          f"{numbers['genuine_sent']}; modes {_modes(numbers['modes'])}; output misses {numbers['output_deadline_misses']} "
          f"of {numbers['cycles']}; opens {t['opens']}, reopens {t['reopens']}, refused {t['refused']}", flush=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--only", default="flood,time_doubled,time_delayed", metavar="R1,R2",
                   help=f"runs, of {', '.join(RUNS)} (default %(default)s)")
    p.add_argument("--trickle", action="store_true", help="also the trickle of 300 connections")
    p.add_argument("--rates", default="100,500,2000", help="flood rates, msg/s (default %(default)s)")
    p.add_argument("--flood-s", type=float, default=20.0)
    p.add_argument("--doubled-s", type=float, default=40.0)
    p.add_argument("--delayed-s", type=float, default=30.0)
    p.add_argument("--delay-ms", type=float, default=100.0)
    p.add_argument("--json", metavar="PATH", help="write every run's numbers here")
    args = p.parse_args()
    runs = [r for r in args.only.split(",") if r] + (["trickle"] if args.trickle else [])
    if unknown := set(runs) - set(RUNS):
        p.error(f"--only: unknown {', '.join(sorted(unknown))}")
    args.rates = [float(r) for r in args.rates.split(",") if r]
    results: dict = {"rsu_clock": {"offset_ms": RSU_OFFSET_MS, "drift_ppm": RSU_DRIFT_PPM}}
    with tempfile.TemporaryDirectory(prefix="v2i-hostile-") as tmp:
        folder = Path(tmp)
        pki = make_pki(folder)
        known = _obu_knows_rsus_option()
        print(f"site: strict, lte-v2x, RSU clock {RSU_OFFSET_MS:g} ms / {RSU_DRIFT_PPM:g} ppm; OBU told its RSU "
              f"(--known-rsus): {'yes' if known else 'no (the option does not exist yet)'}", flush=True)
        if "time_doubled" in runs:
            results["baseline"] = run_baseline(pki, known, args.doubled_s)
            results["time_doubled"] = run_doubled(pki, known, args.doubled_s, folder)
            print_doubled(results["time_doubled"], results["baseline"])
        rest = [r for r in runs if r != "time_doubled"]
        if rest:
            results.update(run_on_one_site(pki, known, args, rest, folder))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
