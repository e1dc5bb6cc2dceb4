"""``v2i demo``: the three services as separate OS processes on loopback Zenoh.

The orchestrator picks free ports and starts RSU, OBU (both ``--await-start``) and link
emulator (``v2i.orchestration.children``); when every one has said it is ready (one bound,
``--ready-timeout``, a progress line meanwhile) it opens its own Zenoh sessions and subscribes,
and only then sends RSU and OBU their common scenario time zero (now + ``START_LEAD_S``), so
that the monitor hears every output from the first cycle on. It scores the OBU's output with
the same code as the offline runner (``RunRecord``):
the Zenoh callbacks only put the payload in a bounded queue (counting what a full queue
drops), a worker thread decodes and scores each message as it arrives, and no message is
kept, so the orchestrator's memory does not grow with the run. Ctrl-C or any child that
dies stops everything; only the processes started here are ended, by pid.

A chaos timeline (``v2i chaos run``, ``v2i.offline.chaos``) is played at scenario time:
link events go as ``LinkControl`` messages to the emulator's control endpoint (a free port
given to it as ``--control-listen``), ``kill`` / ``restart`` SIGKILL a child and start it
again with the same argv (a restarted RSU gets the run's time zero by the same start line once
it is ready again, within the same ``--ready-timeout``); the RSU clock step is in the RSU's start
flags. ``--kill-link-at`` is a generated timeline (kill, restart).
"""

from __future__ import annotations

import itertools
import json
import signal
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from v2i.core.jit import load_kernels
from v2i.offline.kernels import RUN_KERNEL_MODULES
from link_emulator.control_auth import OPERATOR, sign_control
from schemas import keys
from schemas.codec import decode
from schemas.messages import FusedObjectList, LinkControl, ObuMetrics, PredictionList, RsuMetrics
from v2i.runtime.process import log
from v2i.runtime.transport import free_tcp_endpoint, open_session
from v2i.security.pki import Identity, load_signer
from v2i.sim.obu_sources import SimulatedVehicle
from v2i.sim.scenario import load_scenario
from v2i.sim.world import World
from v2i.telemetry.live_line import LiveLine

from v2i.offline.chaos import ChaosEvent, ChaosTimeline
from v2i.reports.chaos_summary import PlayedEvent, chaos_summary, outage_summary
from v2i.orchestration.children import READY_TIMEOUT_S, START_LEAD_S, Child, DemoError, start_all, wait_ready
from v2i.orchestration.inbox_scoring import InboxScoring, obu_own_count, startup_summary
from v2i.orchestration.live_security import run_pki, security_argv
from v2i.offline.spec import RunRecord, RunSpec, build_report

LINK_ID = "link1"
CONTROL_MATCH_S = 3.0  # how long a link control waits for the emulator's control subscriber
POLL_S = 0.02  # supervisor period: chaos events fire within this of their time
METRICS_PORT_OFFSETS = {"rsu": 0, "link": 1, "obu": 2}  # --metrics-ports BASE: each child's /metrics port


@dataclass(frozen=True)
class LinkOutage:
    """Kill the link emulator at ``at_s`` (scenario time) and restart it ``down_s`` later."""

    at_s: float
    down_s: float

    def timeline(self) -> ChaosTimeline:
        """The same fault as a chaos timeline: kill the link, restart it ``down_s`` later."""
        return ChaosTimeline(name="kill-link", events=[ChaosEvent(at_s=self.at_s, kill="link"),
                                                       ChaosEvent(at_s=self.at_s + self.down_s, restart="link")])


class ControlChannel:
    """The demo's Zenoh session to the link emulator's control endpoint.

    Re-opened after the emulator restarts (a session's own reconnection backs off for
    seconds). Sends never block the supervisor for more than ``CONTROL_MATCH_S``; what the
    emulator did with each message comes back in its stats (``control.recent``), kept here.
    """

    def __init__(self, endpoint: str, link_id: str, operator: Identity | None = None):
        self.endpoint, self.link_id = endpoint, link_id
        self.operator = operator  # signs every control (the emulator runs with --pki); None: unsigned
        self.outcomes: dict[int, dict] = {}  # seq -> the emulator's outcome ({"result"} or {"rejected", "error"})
        self._seq = itertools.count(1)
        self._session = self._publisher = self._subscriber = None

    def open(self, timeout_s: float = CONTROL_MATCH_S) -> bool:
        """(Re-)connect; True once the emulator's control subscriber is matched."""
        self.close()
        self._session = open_session(connect=[self.endpoint])
        self._subscriber = self._session.declare_subscriber(keys.link_stats(self.link_id), self._on_stats)
        self._publisher = self._session.declare_publisher(keys.link_control(self.link_id))
        deadline = time.monotonic() + timeout_s
        while not self._publisher.matching_status.matching:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True

    def send(self, control: LinkControl) -> int | None:
        """Put ``control`` with a fresh seq; the seq, or None when the emulator is unreachable."""
        matched = self._publisher is not None and self._publisher.matching_status.matching
        if not matched and not self.open():
            return None
        seq = next(self._seq)
        control = control.model_copy(update={"seq": seq})
        self._publisher.put(sign_control(control, self.operator, time.time_ns()))
        return seq

    def _on_stats(self, sample) -> None:
        try:
            recent = json.loads(sample.payload.to_bytes())["control"]["recent"]
        except (ValueError, KeyError, TypeError):
            return
        for outcome in recent:
            if isinstance(outcome.get("seq"), int):
                self.outcomes[outcome["seq"]] = outcome

    def close(self) -> None:
        for declared in (self._publisher, self._subscriber):
            if declared is not None:
                declared.undeclare()
        if self._session is not None:
            self._session.close()
        self._session = self._publisher = self._subscriber = None


class Demo(InboxScoring):
    def __init__(self, spec: RunSpec, ready_timeout_s: float = READY_TIMEOUT_S, outage: LinkOutage | None = None,
                 chaos: ChaosTimeline | None = None, record_to: str | None = None,
                 progress: str | None = None, metrics_ports: int | None = None, pki_dir: str | None = None,
                 save_wire: str | None = None):
        """``ready_timeout_s``: every service must be ready within this (a restarted one too).
        ``chaos``: a timeline to play; its RSU clock step must already be in ``spec`` (``with_chaos``).
        ``outage`` (``--kill-link-at``) is played as its generated timeline; not with ``chaos``.
        ``record_to``: an MCAP file recording both sides of the link (``v2i.orchestration.demo_recording``).
        ``pki_dir``: the site PKI to use and complete (``live_security.run_pki``); default: one in the
        run's temporary directory. ``save_wire``: the RSU saves every list it sends there (``--save-wire``)."""
        if outage is not None and chaos is not None:
            raise ValueError("a link outage and a chaos timeline together: put the kill and restart in the timeline")
        self.spec = spec
        self.world = World(load_scenario(spec.scenario))
        self.duration_s = spec.duration_s or self.world.scenario.duration_s
        self.ready_timeout_s = ready_timeout_s
        self.ready_s: float | None = None  # launch -> every service ready, s
        self.start_ns: int | None = None  # the run's time zero, sent when every service is ready
        self.record_to = record_to
        self.save_wire = save_wire
        self.metrics_ports = metrics_ports  # /metrics of the children: rsu BASE, link BASE+1, obu BASE+2; None: off
        self.outage = outage
        self.chaos = outage.timeline() if outage else chaos
        self.rsu_ep, self.obu_ep, self.control_ep = free_tcp_endpoint(), free_tcp_endpoint(), free_tcp_endpoint()
        self.children: dict[str, Child] = {}
        self._started: dict[str, Child] = {}
        self.played: list[PlayedEvent] = []
        self.record: RunRecord | None = None  # scored as messages arrive, from run()
        self.progress = progress  # the live line's name (v2i demo; v2i.telemetry.live_line); None: no line
        self._live: LiveLine | None = None  # the live line while the run goes
        self._init_inbox()
        self._down: set[str] = set()  # services killed on purpose and not yet restarted
        self._restarting: dict[str, float] = {}  # service -> monotonic deadline of its ready line
        self._tmp = tempfile.TemporaryDirectory(prefix="v2i-demo-")
        self.link_config = self._write_link_config(Path(self._tmp.name))
        self.pki_dir = run_pki(spec, self.world.scenario, pki_dir or Path(self._tmp.name) / "pki", time.time_ns())
        self._control = ControlChannel(self.control_ep, LINK_ID, load_signer(self.pki_dir, OPERATOR))

    def _write_link_config(self, folder: Path) -> Path:
        """LinkConfig YAML with the RSU position (for distance-dependent channels); no CLI flag has it."""
        rsu = self.world.scenario.rsu.position
        path = folder / "link.yaml"
        path.write_text(json.dumps({"rsu_position": [rsu.x, rsu.y]}))  # JSON is YAML
        return path

    def run(self) -> dict:
        """Start the services, wait until each is ready, subscribe, send time zero, watch, score."""
        # compiled once per machine (v2i.core.jit: tens of seconds) here, not in each child
        load_kernels(RUN_KERNEL_MODULES)
        recorder, sessions, subs = None, [], []
        try:
            for name in ("rsu", "obu", "link"):
                self.children[name] = self._child(name)
            self._wait_ready()
            sessions, subs = self._subscribe()
            start_ns = time.time_ns() + round(START_LEAD_S * 1e9)
            self._start_scoring(start_ns)
            if self.record_to:  # subscribed before the start line, so from the first time query on
                from v2i.orchestration.demo_recording import demo_recorder

                recorder = demo_recorder(self, start_ns, self.record_to)
            start_all(self.children.values(), start_ns)
            self._started = dict(self.children)  # as first started (a chaos restart replaces one)
            if self._has_link_controls():
                log("demo", f"link control endpoint {self.control_ep} (v2i link set --connect {self.control_ep})")
                self._control.open()
            self._supervise(start_ns)
        finally:
            for child in self.children.values():
                child.stop()
            if recorder is not None:
                recorder.stop()
            self._control.close()
            for sub in subs:
                sub.undeclare()
            for session in sessions:
                session.close()
            self._tmp.cleanup()
            self._end_scoring()
        if self._scoring_error is not None:
            raise DemoError(f"scoring the OBU output failed: {self._scoring_error!r}") from self._scoring_error
        return self._report()

    def _child(self, name: str) -> Child:
        """Start service ``name`` (``rsu``, ``obu``, ``link``), its stderr lines labelled with its id."""
        labels = {"rsu": f"rsu {self._rsu_id()}", "obu": f"obu {self.spec.obu_config().vehicle_id}",
                  "link": f"link {LINK_ID}"}
        return Child(name, self._argv(name), label=labels.get(name))

    def _rsu_id(self) -> str:
        """The id the RSU runs with (``image_fusion_demo``: the scenario's)."""
        return self.spec.rsu_config().rsu_id

    def _wait_ready(self) -> None:
        """Every child ready within ``ready_timeout_s`` (a progress line meanwhile), logged."""
        self.ready_s = wait_ready(self.children.values(), self.ready_timeout_s, self.progress)
        log("demo", f"{', '.join(self.children)} ready after {self.ready_s:.1f} s; "
                    f"the run starts {START_LEAD_S:g} s after its start line")

    def _subscribe(self) -> tuple[list, list]:
        """The monitor's sessions and subscriptions (OBU outputs, RSU metrics, link stats), declared
        before time zero so that nothing the run publishes is missed."""
        sessions, subs = [], []
        # Connect once the OBU listens: a session whose first attempt fails retries only after 1, 2, 4 s.
        monitor = open_session(connect=[self.obu_ep])
        sessions.append(monitor)
        vid = self.spec.obu_config().vehicle_id
        subs += [monitor.declare_subscriber(keys.obu_objects(vid), lambda s: self._keep("objects", s)),
                 monitor.declare_subscriber(keys.obu_metrics(vid), lambda s: self._keep("metrics", s)),
                 monitor.declare_subscriber(keys.obu_planning(vid), lambda s: self._keep("planning", s)),
                 *self._more_subscriptions(monitor, vid)]
        if not list(monitor.info.peers_zid()):
            raise DemoError(f"cannot connect to the OBU at {self.obu_ep}")
        if "rsu" in self.children:
            rsu_monitor = open_session(connect=[self.rsu_ep])  # the RSU's metrics stay on its side of the link
            sessions.append(rsu_monitor)
            subs.append(rsu_monitor.declare_subscriber(keys.rsu_metrics(self.spec.rsu_config().rsu_id),
                                                       lambda s: self._keep("rsu_metrics", s)))
        if "link" in self.children:  # the emulator's stats (their latency_ms) on its control side
            link_monitor = open_session(connect=[self.control_ep])
            sessions.append(link_monitor)
            subs.append(link_monitor.declare_subscriber(keys.link_stats(LINK_ID),
                                                        lambda s: self._keep("link_stats", s)))
        return sessions, subs

    def _start_scoring(self, start_ns: int) -> None:
        """The run's record from time zero ``start_ns`` and the scorer thread (what the subscriptions
        queued meanwhile is scored first)."""
        self.start_ns = start_ns
        cycles = SimulatedVehicle(self.world, self.spec.seed, start_ns).cycle_times_ns(self.duration_s)
        self.record = RunRecord(self.world, start_ns, self.duration_s, cycles)
        self._start_scorer()

    def _more_subscriptions(self, monitor, vehicle_id: str) -> list:
        """Further OBU outputs a subclass watches (``image_fusion_demo``); none here."""
        return []

    def _has_link_controls(self) -> bool:
        return self.chaos is not None and any(e.link_control(LINK_ID) is not None for e in self.chaos.events)

    def _argv(self, name: str) -> list[str]:
        """``name``'s command line, with its ``--metrics-port`` when the demo has ``metrics_ports``."""
        argv = self._service_argv(name)
        if self.metrics_ports is None:
            return argv
        return [*argv, "--metrics-port", str(self.metrics_ports + METRICS_PORT_OFFSETS[name])]

    def _service_argv(self, name: str) -> list[str]:
        """RSU and OBU wait for their start line (``--await-start``); the emulator needs no time zero."""
        s, base = self.spec, [sys.executable, "-m", "v2i", name]
        common = ["--scenario", s.scenario, "--seed", str(s.seed), "--await-start", "--duration", str(self.duration_s)]
        if name == "rsu":
            ahead = ["--predict-ahead"] if s.rsu_config().predict_ahead else []
            step = [] if s.rsu_clock_step_at_s is None else ["--clock-step-ms", str(s.rsu_clock_step_ms),
                                                              "--clock-step-at-s", str(s.rsu_clock_step_at_s)]
            return base + ["--listen", self.rsu_ep, *common, "--clock-offset-ms", str(s.rsu_clock_offset_ms),
                           "--clock-drift-ppm", str(s.rsu_clock_drift_ppm), *step, *ahead, "--source", s.rsu_source,
                           "--wire", s.wire, *(["--cpm-rules"] if s.cpm_rules else []),
                           *security_argv(s, name, self.pki_dir),
                           *(["--save-wire", str(self.save_wire)] if self.save_wire else [])]
        if name == "obu":
            return base + ["--listen", self.obu_ep, *common, "--fusion", s.fusion, "--compensation", s.compensation,
                           "--fusion-mode", s.fusion_mode, "--deadline-ms", str(s.deadline_ms), "--wires", s.wire,
                           *security_argv(s, name, self.pki_dir)]
        return base + ["--config", str(self.link_config), "--link-id", LINK_ID, "--rsu-connect", self.rsu_ep,
                       "--vehicle-connect", self.obu_ep, "--control-listen", self.control_ep,
                       "--pki", str(self.pki_dir), "--profile", s.profile, "--seed", str(s.seed),
                       "--vehicle-id", s.obu_config().vehicle_id]

    def _score(self, kind: str, data: bytes) -> None:
        if kind == "objects":
            self.record.add_output(decode(data, FusedObjectList))
        elif kind == "planning":
            self.record.add_planning(decode(data, PredictionList))
        elif kind == "rsu_metrics":
            metrics = decode(data, RsuMetrics)
            if metrics.perception is not None:  # each message holds the run's totals so far
                self.record.rsu_perception = metrics.perception.model_dump()
            if metrics.latency_ms:
                self.record.latency_ms["rsu"] = {stage: q.model_dump() for stage, q in metrics.latency_ms.items()}
        elif kind == "link_stats":  # the emulator's JSON stats: its latency_ms as it is
            try:
                latency_ms = json.loads(data).get("latency_ms")
            except (ValueError, AttributeError):
                return
            if isinstance(latency_ms, dict) and latency_ms:
                self.record.latency_ms["link"] = latency_ms
        else:
            metrics = decode(data, ObuMetrics)
            self.record.add_obu_metrics(metrics)
            if self._live is not None:
                self._live.feed(metrics)

    def _supervise(self, start_ns: int) -> None:
        """Log the endpoints (for ``v2i monitor``); show the live line (``progress``) while ``_watch`` runs."""
        log("demo", f"endpoints: OBU {self.obu_ep}, RSU {self.rsu_ep}, link {self.control_ep} "
                    f"(v2i monitor --connect {self.obu_ep} --connect {self.rsu_ep} --connect {self.control_ep})")
        events = len(self.chaos.events) if self.chaos else 0
        self._watch_with_live_line(start_ns, lambda: (len(self.played), events))

    def _watch(self, start_ns: int) -> None:
        """Watch the children until the run ends, playing the chaos timeline at scenario time."""
        end_ns = start_ns + round((self.duration_s + 0.5) * 1e9)
        plan = [(start_ns + round(e.at_s * 1e9), e) for e in (self.chaos.sorted_events() if self.chaos else [])]
        while (now_ns := time.time_ns()) < end_ns:
            self._check_children()
            while plan and now_ns >= plan[0][0]:
                self._play(plan.pop(0)[1], start_ns)
            next_ns = min(plan[0][0] if plan else end_ns, end_ns)
            time.sleep(min(POLL_S, max(next_ns - time.time_ns(), 0) * 1e-9))

    def _check_children(self) -> None:
        """A child that died while meant to be up ends the demo; restarted ones must become ready."""
        for name, child in self.children.items():
            if name in self._down:
                continue
            if name in self._restarting:
                if child.poll_ready():
                    del self._restarting[name]
                    child.start(self.start_ns)  # the run's time zero, long past: it goes on from now
                    log("demo", f"chaos: {name} is back (pid {child.proc.pid})")
                    if name == "link" and self._has_link_controls():
                        self._control.open()
                elif time.monotonic() > self._restarting[name]:
                    raise DemoError(f"{name} was not ready {self.ready_timeout_s:g} s after its restart "
                                    f"(--ready-timeout){child.tail()}")
            elif child.proc.poll() is not None:
                raise DemoError(f"{name} exited with code {child.proc.returncode} during the run{child.tail()}")

    def _play(self, event: ChaosEvent, start_ns: int) -> None:
        """Fire one chaos event now and remember when."""
        played = PlayedEvent(event, round((time.time_ns() - start_ns) * 1e-9, 3))
        control = event.link_control(LINK_ID)
        if control is not None:
            link_up = "link" not in self._down and "link" not in self._restarting
            played.seq = self._control.send(control) if link_up else None
            if played.seq is None:
                why = f"unreachable at {self.control_ep}" if link_up else "down"
                log("demo", f"chaos: {event.describe()} not sent: the link emulator is {why}")
            else:
                log("demo", f"chaos: {event.describe()} sent to the link emulator")
        elif event.kill:
            self._kill(event.kill)
        elif event.restart:
            self._restart(event.restart)
        else:
            log("demo", f"chaos: {event.describe()} (set at the RSU's start)")
        self.played.append(played)

    def _kill(self, name: str) -> None:
        log("demo", f"chaos: killing {name} (pid {self.children[name].proc.pid})")
        self._down.add(name)
        self._restarting.pop(name, None)
        self.children[name].stop(signal.SIGKILL)

    def _restart(self, name: str) -> None:
        """Start ``name`` again with its argv; the supervisor sends it the run's time zero once it is
        ready (within ``ready_timeout_s``)."""
        log("demo", f"chaos: restarting {name}")
        self.children[name] = self._child(name)
        self._restarting[name] = time.monotonic() + self.ready_timeout_s
        self._down.discard(name)

    def _report(self) -> dict:
        record = self.record
        report = build_report(self.spec, self.world, record, driver="demo")
        report["monitor_messages_dropped"] = dict(self.dropped)
        report["obu_output_deadline_misses"] = {self.spec.obu_config().vehicle_id: obu_own_count(record)}
        report["startup"] = startup_summary(self.ready_s, self._started.values())
        if sum(self.dropped.values()):
            log("demo", f"the scorer fell behind: dropped {dict(self.dropped)} (scores miss them)")
        if self.outage:
            report["link_outage"] = outage_summary(record, self.outage.at_s, self.outage.down_s)
        elif self.chaos:
            report["chaos"] = self.chaos.name
            report["chaos_events"] = chaos_summary(self.played, self.chaos, record, self._control.outcomes, LINK_ID)
        return report


