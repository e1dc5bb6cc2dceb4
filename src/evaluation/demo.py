"""``v2i demo``: the three services as separate OS processes on loopback Zenoh.

The orchestrator picks free ports, starts RSU, OBU and link emulator with a common
scenario start time a few seconds ahead, watches the OBU's output through its own
Zenoh session, and scores it with the same code as the offline runner. Ctrl-C or any
child that dies stops everything; only the processes started here are ended, by pid.
"""

from __future__ import annotations

import json
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from obu_service.fusion_mode import MODES
from obu_service.source import SimulatedVehicle
from schemas import keys
from schemas.codec import CodecError, decode
from schemas.messages import FusedObjectList, ObuMetrics, PredictionList
from schemas.runtime import log
from schemas.transport import free_tcp_endpoint, open_session
from sim.scenario import load_scenario
from sim.world import World

from .spec import RunRecord, RunSpec, build_report


TRACKING_MODES = ("intra", "inter")  # the modes that feed RSU data to the tracker


class DemoError(RuntimeError):
    """A demo that could not run to the end (a child failed, or never became ready)."""


@dataclass(frozen=True)
class LinkOutage:
    """Kill the link emulator at ``at_s`` (scenario time) and restart it ``down_s`` later."""

    at_s: float
    down_s: float


class Child:
    """One service process; its stdout lines are read by a thread into a queue."""

    def __init__(self, name: str, argv: list[str]):
        self.name, self.argv = name, argv
        self.lines: queue.Queue[str] = queue.Queue()
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, text=True, start_new_session=True)
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line)

    def wait_ready(self, deadline: float) -> None:
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise DemoError(f"{self.name} exited with code {self.proc.returncode} before it was ready")
            try:
                line = self.lines.get(timeout=0.05)
            except queue.Empty:
                continue
            if json.loads(line).get("event") == "ready":
                return
        raise DemoError(f"{self.name} was not ready in time (raise --startup)")

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 5.0) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class Demo:
    def __init__(self, spec: RunSpec, startup_s: float = 4.0, outage: LinkOutage | None = None):
        self.spec = spec
        self.world = World(load_scenario(spec.scenario))
        self.duration_s = spec.duration_s or self.world.scenario.duration_s
        self.startup_s = startup_s
        self.outage = outage
        self.rsu_ep, self.obu_ep = free_tcp_endpoint(), free_tcp_endpoint()
        self.children: dict[str, Child] = {}
        self._received: list[tuple[str, bytes, int]] = []
        self._link_down = False
        self._tmp = tempfile.TemporaryDirectory(prefix="v2i-demo-")
        self.link_config = self._write_link_config(Path(self._tmp.name))

    def _write_link_config(self, folder: Path) -> Path:
        """LinkConfig YAML with the RSU position (for distance-dependent channels); no CLI flag has it."""
        rsu = self.world.scenario.rsu.position
        path = folder / "link.yaml"
        path.write_text(json.dumps({"rsu_position": [rsu.x, rsu.y]}))  # JSON is YAML
        return path

    def run(self) -> dict:
        start_ns = time.time_ns() + round(self.startup_s * 1e9)
        monitor = open_session(connect=[self.obu_ep])
        vid = self.spec.obu_config().vehicle_id
        subs = [monitor.declare_subscriber(keys.obu_objects(vid), lambda s: self._keep("objects", s)),
                monitor.declare_subscriber(keys.obu_metrics(vid), lambda s: self._keep("metrics", s)),
                monitor.declare_subscriber(keys.obu_planning(vid), lambda s: self._keep("planning", s))]
        try:
            for name in ("rsu", "obu", "link"):
                self.children[name] = Child(name, self._argv(name, start_ns))
            deadline = time.monotonic() + (start_ns - time.time_ns()) * 1e-9
            for child in self.children.values():
                child.wait_ready(deadline)
            self._supervise(start_ns)
        finally:
            for child in self.children.values():
                child.stop()
            for sub in subs:
                sub.undeclare()
            monitor.close()
            self._tmp.cleanup()
        return self._report(start_ns)

    def _argv(self, name: str, start_ns: int) -> list[str]:
        s, base = self.spec, [sys.executable, "-m", "v2i", name]
        common = ["--scenario", s.scenario, "--seed", str(s.seed), "--start-at-ns", str(start_ns),
                  "--duration", str(self.duration_s)]
        if name == "rsu":
            ahead = ["--predict-ahead"] if s.rsu_config().predict_ahead else []
            step = [] if s.rsu_clock_step_at_s is None else ["--clock-step-ms", str(s.rsu_clock_step_ms),
                                                              "--clock-step-at-s", str(s.rsu_clock_step_at_s)]
            return base + ["--listen", self.rsu_ep, *common, "--clock-offset-ms", str(s.rsu_clock_offset_ms),
                           "--clock-drift-ppm", str(s.rsu_clock_drift_ppm), *step, *ahead]
        if name == "obu":
            return base + ["--listen", self.obu_ep, *common, "--fusion", s.fusion, "--compensation", s.compensation,
                           "--fusion-mode", s.fusion_mode, "--deadline-ms", str(s.deadline_ms)]
        return base + ["--config", str(self.link_config), "--rsu-connect", self.rsu_ep, "--vehicle-connect",
                       self.obu_ep, "--profile", s.profile, "--seed", str(s.seed)]

    def _keep(self, kind: str, sample) -> None:
        self._received.append((kind, sample.payload.to_bytes(), time.time_ns()))

    def _supervise(self, start_ns: int) -> None:
        """Watch the children until the run ends; play the link outage if one is asked for."""
        end_ns = start_ns + round((self.duration_s + 0.5) * 1e9)
        chaos = []
        if self.outage:
            kill_ns = start_ns + round(self.outage.at_s * 1e9)
            chaos = [(kill_ns, self._kill_link), (kill_ns + round(self.outage.down_s * 1e9), self._restart_link)]
        while time.time_ns() < end_ns:
            for name, child in self.children.items():
                if child.proc.poll() is not None and not (name == "link" and self._link_down):
                    raise DemoError(f"{name} exited with code {child.proc.returncode} during the run")
            while chaos and time.time_ns() >= chaos[0][0]:
                chaos.pop(0)[1](start_ns)
            time.sleep(0.02)

    def _kill_link(self, _start_ns: int) -> None:
        log("demo", f"chaos: killing the link emulator (pid {self.children['link'].proc.pid})")
        self._link_down = True
        self.children["link"].stop(signal.SIGKILL)

    def _restart_link(self, start_ns: int) -> None:
        log("demo", "chaos: restarting the link emulator")
        self.children["link"] = Child("link", self._argv("link", start_ns))
        self.children["link"].wait_ready(time.monotonic() + 10.0)
        self._link_down = False

    def _report(self, start_ns: int) -> dict:
        cycles = SimulatedVehicle(self.world, self.spec.seed, start_ns).cycle_times_ns(self.duration_s)
        record = RunRecord(start_ns, self.duration_s, [int(t) for t in cycles])
        last = None
        for kind, data, _ in self._received:
            try:
                if kind == "objects":
                    record.outputs.append(decode(data, FusedObjectList))
                elif kind == "planning":
                    record.planning.append(decode(data, PredictionList))
                else:
                    last = decode(data, ObuMetrics)
                    record.offset_samples += [(last.t_ns, r.clock_offset_ns, r.clock_offset_naive_ns, r.clock_drift_ppm)
                                              for r in last.rsus if r.clock_offset_ns is not None]
            except CodecError as exc:
                log("demo", f"undecodable {kind} message: {exc}")
        if last is not None:
            record.rsu_messages = max((r.messages_accepted for r in last.rsus), default=0)
            record.covered_cycles, record.rsu_deadline_misses = last.covered_cycles, last.rsu_deadline_misses
        report = build_report(self.spec, self.world, record, driver="demo")
        if self.outage:
            report["link_outage"] = outage_summary(record.outputs, start_ns, self.outage)
        return report


def outage_summary(outputs: list[FusedObjectList], start_ns: int, outage: LinkOutage) -> dict:
    """Cycles and modes during the outage, and how soon tracking fusion (intra or inter)
    resumed after it."""
    t = lambda m: (m.cycle_time_ns - start_ns) * 1e-9  # noqa: E731
    end_s = outage.at_s + outage.down_s
    during = [m for m in outputs if outage.at_s <= t(m) < end_s]
    fused_after = [t(m) for m in outputs if t(m) >= end_s and m.mode in TRACKING_MODES]
    return {
        "kill_at_s": outage.at_s, "down_s": outage.down_s, "cycles_published_during": len(during),
        "cycles_expected_during": round(outage.down_s * 10),
        "mode_share_during": {mode.replace("-", "_"): round(sum(m.mode == mode for m in during) / max(len(during), 1), 4)
                              for mode in MODES},
        "fused_again_after_s": round(fused_after[0] - end_s, 3) if fused_after else None,
    }
