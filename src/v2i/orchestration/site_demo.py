"""``v2i demo`` of a site: every RSU, one link emulator per RSU and every vehicle's OBU as
separate OS processes on loopback Zenoh, scored per vehicle like ``v2i eval`` scores them.

Processes (R RSUs, V vehicles): R ``v2i rsu --rsu-id X`` (each listens on its own port),
V ``v2i obu --vehicle-id NAME`` (each listens on its own port and senses as that vehicle of
the scenario), and R ``v2i link`` (emulator ``link-X`` connects to RSU X and to every OBU,
``--vehicle NAME=EP`` once per vehicle: one channel per RSU-vehicle pair). The emulators
are the only path between the RSU and vehicle sides. With V2V (the scenario's ``v2v``, or
``--v2v on``) the OBUs run ``--v2v`` and one more emulator, ``link-v2v`` (``v2i link --v2v``,
one per site: ``link_emulator.v2v_relay``), connects to every OBU and is the only path between
vehicles, a channel per ordered vehicle pair with the scenario's V2V profile; the watcher also
reaches it on its control endpoint for its stats (``v2v_link`` in the report: per pair
received / delivered / dropped and delay) and hears each OBU's peers (``v2x/obu/{id}/peers``:
``vehicles.{id}.peers``, as ``v2i eval``; ``v2v_rejected`` from its metrics).

One watcher session connects to every OBU and every RSU (a peer does not forward between
the peers it connects to, Zenoh's default ``peer_to_peer`` routing, so it adds no path
around the emulators). As in ``v2i.orchestration.demo``: the callbacks only enqueue the payload
into a bounded inbox (a full inbox drops, counted), a scorer thread decodes and scores,
each vehicle has its ``RunRecord`` (fused lists routed by their ``vehicle_id``), each OBU's
metrics feed its record, each RSU's metrics give its perception scores. The report is
``site_report`` (the keys of ``v2i eval`` on the same scenario), plus the monitor's drops
and the RSU lists each OBU accepted per RSU. Every child is stopped in ``finally``, by pid;
nothing else is touched. Chaos timelines are single-link only (``v2i.orchestration.demo``).

Security as in ``v2i.orchestration.demo``: one site PKI for every node (``live_security.run_pki``: every
RSU and vehicle of the scenario, the operator), each RSU signs and each OBU verifies under
``spec.security`` (``live_security.security_argv``); every link emulator gets ``--pki`` too, so
it applies only the operator's signed control (``v2i link set --pki DIR``). The report's ``security_outcomes`` (the
offline runner's key) holds, per vehicle, its OBU's verification failures by reason (dropped or,
under ``permissive``, accepted), from its last metrics; the OBU does not publish its ``ok`` count.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

from v2i.core.jit import load_kernels
from v2i.offline.kernels import RUN_KERNEL_MODULES
from v2i.perception.scoring import PerceptionTally
from schemas import keys
from schemas.codec import decode
from schemas.messages import FusedObjectList, ObuMetrics, PredictionList, RsuMetrics
from v2i.runtime.process import log
from v2i.runtime.transport import free_tcp_endpoint, open_session
from v2i.sim.obu_sources import SimulatedVehicle
from v2i.sim.scenario import Scenario, load_scenario
from v2i.sim.world import World
from v2i.telemetry.live_line import LiveLine

from v2i.orchestration.children import READY_TIMEOUT_S, START_LEAD_S, Child, DemoError, start_all, wait_ready
from v2i.orchestration.demo import POLL_S
from v2i.orchestration.inbox_scoring import InboxScoring, obu_own_count, startup_summary
from v2i.orchestration.live_security import run_pki, security_argv
from v2i.offline.runner import v2v_config
from v2i.offline.spec import RunRecord, RunSpec, site_report

STOP_WAIT_S = 5.0  # a child still running this long after SIGTERM is killed
CONNECT_WAIT_S = 3.0  # the watcher must reach every service within this


def is_site(scenario: Scenario) -> bool:
    """True when the scenario has more than one RSU or more than one vehicle (a ``SiteDemo``)."""
    return len(scenario.rsus) > 1 or len(scenario.vehicles) > 1


V2V_LINK_ID = "link-v2v"  # the site's V2V emulator


def link_id(rsu_id: str) -> str:
    """The emulator serving RSU ``rsu_id`` (names ``v2x/link/{link_id}/*``)."""
    return f"link-{rsu_id}"


class SiteDemo(InboxScoring):
    """Every node of ``spec.scenario`` as its own process; ``run()`` returns the site report."""

    def __init__(self, spec: RunSpec, ready_timeout_s: float = READY_TIMEOUT_S, progress: str | None = None,
                 pki_dir: str | None = None, save_wire: str | None = None):
        """``ready_timeout_s``: every service must be ready within this; the run starts when all are.
        ``progress``: the live line's name (``v2i.telemetry.live_line``), None for no line.
        ``pki_dir``: the site PKI to use and complete; default: one in the run's temporary directory.
        ``save_wire``: every RSU saves each list it sends there (``--save-wire``), in its own subfolder."""
        self.save_wire = save_wire
        self.progress = progress
        self._live: LiveLine | None = None
        self.spec = spec
        self.scenario = load_scenario(spec.scenario)
        self.duration_s = spec.duration_s or self.scenario.duration_s
        self.ready_timeout_s = ready_timeout_s
        self.ready_s: float | None = None  # launch -> every service ready, s
        self.rsu_ids = [rsu.id for rsu in self.scenario.rsus]
        self.vehicle_ids = [v.name for v in self.scenario.vehicles]
        self.worlds = {name: World(self.scenario, ego=name) for name in self.vehicle_ids}
        endpoints = _distinct_endpoints(len(self.rsu_ids) + len(self.vehicle_ids))
        self.rsu_eps = dict(zip(self.rsu_ids, endpoints))
        self.obu_eps = dict(zip(self.vehicle_ids, endpoints[len(self.rsu_ids):]))
        self.v2v = v2v_config(self.scenario.v2v, spec.v2v) if len(self.vehicle_ids) > 1 else None
        self.v2v_ep = _distinct_endpoints(len(endpoints) + 1)[-1] if self.v2v is not None else None
        self.v2v_stats: dict | None = None  # the V2V emulator's latest stats
        self.peers: dict[str, dict] = {}  # vehicle -> its OBU's latest peers summary
        self.obu_rejected: dict[str, dict[str, int]] = {}  # vehicle -> its OBU's refusals (latest metrics)
        self.children: dict[str, Child] = {}
        self.records: dict[str, RunRecord] = {}
        self.rsu_perception: dict[str, dict] = {}  # rsu id -> its latest totals (RsuMetrics.perception)
        self.rsu_lists_accepted: dict[str, dict[str, int]] = {}  # vehicle -> rsu id -> lists its OBU accepted
        self.unknown: Counter = Counter()  # messages naming a vehicle or RSU not in the scenario, by kind
        self._init_inbox()
        self._tmp = tempfile.TemporaryDirectory(prefix="v2i-site-demo-")
        self.pki_dir = run_pki(spec, self.scenario, pki_dir or Path(self._tmp.name) / "pki", time.time_ns())

    def run(self) -> dict:
        """Start every node, wait until each is ready, connect the watcher, send time zero, watch, score."""
        # compiled once per machine (v2i.core.jit: tens of seconds) here, not in each child
        load_kernels(RUN_KERNEL_MODULES)
        watcher, subs = None, []
        try:
            self._start_children()
            self.ready_s = wait_ready(self.children.values(), self.ready_timeout_s, self.progress)
            log("demo", "endpoints (v2i monitor --connect EP ...): OBUs " + ", ".join(
                f"{n} {ep}" for n, ep in self.obu_eps.items()) + "; RSUs " + ", ".join(
                f"{r} {ep}" for r, ep in self.rsu_eps.items()))
            log("demo", f"all {len(self.children)} processes ready after {self.ready_s:.1f} s; "
                        f"the run starts {START_LEAD_S:g} s after its start line")
            # connect once every service listens: a failed first attempt is retried only after 1, 2, 4 s
            watcher = open_session(connect=[*self.obu_eps.values(), *self.rsu_eps.values(),
                                            *([self.v2v_ep] if self.v2v_ep else [])])
            subs = self._subscribe(watcher)
            self._wait_connected(watcher)
            start_ns = time.time_ns() + round(START_LEAD_S * 1e9)
            self._start_records(start_ns)
            start_all(self.children.values(), start_ns)
            self._supervise(start_ns)
        finally:
            self._stop_children()
            for sub in subs:
                sub.undeclare()
            if watcher is not None:
                watcher.close()
            self._tmp.cleanup()
            self._end_scoring()
        if self._scoring_error is not None:
            raise DemoError(f"scoring the OBU outputs failed: {self._scoring_error!r}") from self._scoring_error
        return self._report()

    def _start_records(self, start_ns: int) -> None:
        """Each vehicle's record from time zero ``start_ns``, then the scorer (queued messages first)."""
        self.start_ns = start_ns
        for name, world in self.worlds.items():
            cycles = SimulatedVehicle(world, self.spec.seed, start_ns).cycle_times_ns(self.duration_s)
            self.records[name] = RunRecord(world, start_ns, self.duration_s, cycles)
        self._start_scorer()

    # --- processes -----------------------------------------------------------------------
    def _start_children(self) -> None:
        """RSUs and OBUs first (they listen; ``--await-start``), then the emulators (they connect to
        both sides). Each child's log lines are labelled with its node: ``[rsu rsu-nw]``, ``[obu car-2]``,
        ``[link link-rsu-nw]``."""
        for rsu_id in self.rsu_ids:
            self.children[f"rsu {rsu_id}"] = Child(f"rsu {rsu_id}", self._rsu_argv(rsu_id))
        for name in self.vehicle_ids:
            self.children[f"obu {name}"] = Child(f"obu {name}", self._obu_argv(name))
        for rsu_id in self.rsu_ids:
            self.children[link_id(rsu_id)] = Child(link_id(rsu_id), self._link_argv(rsu_id),
                                                   label=f"link {link_id(rsu_id)}")
        if self.v2v is not None:
            self.children[V2V_LINK_ID] = Child(V2V_LINK_ID, self._v2v_link_argv(), label=f"link {V2V_LINK_ID}")
        log("demo", f"site {self.spec.scenario}: {len(self.children)} processes, pids "
                    + ", ".join(f"{name} {c.proc.pid}" for name, c in self.children.items()))

    def _common(self) -> list[str]:
        s = self.spec
        return ["--scenario", s.scenario, "--seed", str(s.seed), "--await-start", "--duration", str(self.duration_s)]

    def _rsu_argv(self, rsu_id: str) -> list[str]:
        s = self.spec
        ahead = ["--predict-ahead"] if s.rsu_config().predict_ahead else []
        step = [] if s.rsu_clock_step_at_s is None else ["--clock-step-ms", str(s.rsu_clock_step_ms),
                                                          "--clock-step-at-s", str(s.rsu_clock_step_at_s)]
        return [sys.executable, "-m", "v2i", "rsu", "--rsu-id", rsu_id, "--listen", self.rsu_eps[rsu_id],
                *self._common(), "--clock-offset-ms", str(s.rsu_clock_offset_ms),
                "--clock-drift-ppm", str(s.rsu_clock_drift_ppm), *step, *ahead, "--source", s.rsu_source,
                "--wire", s.wire, *(["--cpm-rules"] if s.cpm_rules else []),
                *security_argv(s, "rsu", self.pki_dir),
                *(["--save-wire", str(self.save_wire)] if self.save_wire else [])]

    def _obu_argv(self, name: str) -> list[str]:
        s = self.spec
        v2v = [] if self.v2v is None else ["--v2v", "--max-peers", str(self.v2v.max_peers)]
        return [sys.executable, "-m", "v2i", "obu", "--vehicle-id", name, "--listen", self.obu_eps[name],
                *self._common(), "--fusion", s.fusion, "--compensation", s.compensation,
                "--fusion-mode", s.fusion_mode, "--deadline-ms", str(s.deadline_ms), "--wires", s.wire, *v2v,
                *security_argv(s, "obu", self.pki_dir)]

    def _v2v_link_argv(self) -> list[str]:
        """The site's V2V emulator: every OBU, a channel per ordered pair, the scenario's V2V profile."""
        vehicles = [arg for name, ep in self.obu_eps.items() for arg in ("--vehicle", f"{name}={ep}")]
        return [sys.executable, "-m", "v2i", "link", "--v2v", "--link-id", V2V_LINK_ID, *vehicles,
                "--profile", self.v2v.link_profile, "--seed", str(self.spec.seed), "--control-listen", self.v2v_ep,
                "--pki", str(self.pki_dir)]

    def _link_argv(self, rsu_id: str) -> list[str]:
        """Emulator of RSU ``rsu_id``: its position (distance-dependent channels; no CLI flag has
        it) and profile (the RSU's ``link_profile``, else the run's, as ``v2i eval``)."""
        rsu = self.scenario.rsu_by_id(rsu_id)
        config = Path(self._tmp.name) / f"{link_id(rsu_id)}.yaml"
        config.write_text(json.dumps({"rsu_position": [rsu.position.x, rsu.position.y]}))  # JSON is YAML
        vehicles = [arg for name, ep in self.obu_eps.items() for arg in ("--vehicle", f"{name}={ep}")]
        return [sys.executable, "-m", "v2i", "link", "--config", str(config), "--link-id", link_id(rsu_id),
                "--rsu-connect", self.rsu_eps[rsu_id], *vehicles, "--profile", rsu.link_profile or self.spec.profile,
                "--seed", str(self.spec.seed), "--pki", str(self.pki_dir)]

    def _supervise(self, start_ns: int) -> None:
        """The live line (``progress``) while ``_watch`` runs."""
        self._watch_with_live_line(start_ns)

    def _watch(self, start_ns: int) -> None:
        """Until the run's end (+0.5 s; the services end at +1 s): any child that exits ends the demo."""
        end_ns = start_ns + round((self.duration_s + 0.5) * 1e9)
        while time.time_ns() < end_ns:
            for name, child in self.children.items():
                if child.proc.poll() is not None:
                    raise DemoError(f"{name} exited with code {child.proc.returncode} during the run{child.tail()}")
            time.sleep(POLL_S)

    def _stop_children(self) -> None:
        """SIGTERM every child started here at once, then wait for each; SIGKILL what outlives STOP_WAIT_S."""
        alive = [c for c in self.children.values() if c.proc.poll() is None]
        for child in alive:
            child.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + STOP_WAIT_S
        for child in alive:
            try:
                child.proc.wait(max(deadline - time.monotonic(), 0.0))
            except subprocess.TimeoutExpired:
                log("demo", f"{child.name} (pid {child.proc.pid}) ignored SIGTERM for {STOP_WAIT_S:g} s: killed")
                child.proc.kill()
                child.proc.wait()

    # --- watching and scoring ------------------------------------------------------------
    def _subscribe(self, watcher) -> list:
        subs = []
        for name in self.vehicle_ids:
            for kind, key in (("objects", keys.obu_objects(name)), ("metrics", keys.obu_metrics(name)),
                              ("planning", keys.obu_planning(name))):
                subs.append(watcher.declare_subscriber(key, lambda s, k=kind, n=name: self._keep(k, s, n)))
        for rsu_id in self.rsu_ids:
            subs.append(watcher.declare_subscriber(keys.rsu_metrics(rsu_id),
                                                   lambda s, r=rsu_id: self._keep("rsu_metrics", s, r)))
        if self.v2v is not None:
            subs.append(watcher.declare_subscriber(keys.link_stats(V2V_LINK_ID),
                                                   lambda s: self._keep("v2v_stats", s, V2V_LINK_ID)))
            for name in self.vehicle_ids:
                subs.append(watcher.declare_subscriber(keys.obu_peers(name),
                                                       lambda s, n=name: self._keep("peers", s, n)))
        return subs

    def _wait_connected(self, watcher) -> None:
        """Every OBU and RSU must be a peer of the watcher (else its scores would silently be empty)."""
        wanted = len(self.obu_eps) + len(self.rsu_eps) + (self.v2v_ep is not None)
        deadline = time.monotonic() + CONNECT_WAIT_S
        while (peers := len(list(watcher.info.peers_zid()))) < wanted:
            if time.monotonic() > deadline:
                raise DemoError(f"the watcher reached {peers} of {wanted} services "
                                f"({', '.join([*self.obu_eps.values(), *self.rsu_eps.values()])})")
            time.sleep(0.05)

    def _score(self, kind: str, node: str, data: bytes) -> None:
        """``node``: the vehicle (or RSU) whose key the message came on; fused lists and OBU
        metrics go to the record of the vehicle they name."""
        if kind == "rsu_metrics":
            metrics = decode(data, RsuMetrics)
            if metrics.perception is not None:  # each message holds the run's totals so far
                self.rsu_perception[metrics.rsu_id] = metrics.perception.model_dump()
            return
        if kind in ("v2v_stats", "peers"):  # JSON, the latest kept
            value = json.loads(data)
            if kind == "v2v_stats":
                self.v2v_stats = value
            elif node in self.records:
                self.peers[node] = value
            return
        if kind == "planning":
            self.records[node].add_planning(decode(data, PredictionList))
            return
        message = decode(data, FusedObjectList if kind == "objects" else ObuMetrics)
        record = self.records.get(message.vehicle_id)
        if record is None:
            self.unknown[kind] += 1
        elif kind == "objects":
            record.add_output(message)
        else:
            record.add_obu_metrics(message)
            if self._live is not None:
                self._live.feed(message)
            self.rsu_lists_accepted[message.vehicle_id] = {r.rsu_id: r.messages_accepted for r in message.rsus}
            self.obu_rejected[message.vehicle_id] = dict(message.rejected)

    def _report(self) -> dict:
        """``site_report`` (the ego's record carries the first RSU's perception, as in ``v2i eval``)."""
        first = self.rsu_ids[0]
        if first in self.rsu_perception:
            self.records[self.vehicle_ids[0]].rsu_perception = self.rsu_perception[first]
        rsus = {rsu_id: self.rsu_perception.get(rsu_id) or PerceptionTally().scores() for rsu_id in self.rsu_ids}
        vehicles = [(name, self.worlds[name], self.records[name]) for name in self.vehicle_ids]
        report = site_report(self.spec, vehicles, rsus, driver="demo")
        report["monitor_messages_dropped"] = dict(self.dropped)
        report["obu_output_deadline_misses"] = {name: obu_own_count(self.records[name]) for name in self.vehicle_ids}
        report["startup"] = startup_summary(self.ready_s, self.children.values())
        report["rsu_lists_accepted"] = {name: self.rsu_lists_accepted.get(name, {}) for name in self.vehicle_ids}
        report["v2v"] = None if self.v2v is None else self.v2v.model_dump()
        report["security_outcomes"] = (None if self.spec.security is None else
                                       {name: _security_failures(self.obu_rejected.get(name, {}))
                                        for name in self.vehicle_ids})
        if self.v2v is not None:
            report["v2v_link"] = _v2v_link_summary(self.v2v_stats)
            for name in self.vehicle_ids:
                rejected = self.obu_rejected.get(name, {})
                report["vehicles"][name]["peers"] = self.peers.get(name, {})
                report["vehicles"][name]["v2v_rejected"] = {k: n for k, n in rejected.items() if k.startswith("v2v_")}
        if sum(self.dropped.values()):
            log("demo", f"the scorer fell behind: dropped {dict(self.dropped)} (scores miss them)")
        if sum(self.unknown.values()):
            log("demo", f"messages naming no vehicle of the scenario: {dict(self.unknown)}")
        return report


def _security_failures(rejected: dict[str, int]) -> dict[str, int]:
    """Verification failures by reason from an OBU's refusals: ``security_<reason>`` (dropped) and
    ``security_accepted_<reason>`` (let through under permissive) both count as ``<reason>``."""
    out: Counter = Counter()
    for label, n in rejected.items():
        if label.startswith("security_"):
            out[label.removeprefix("security_").removeprefix("accepted_")] += n
    return dict(sorted(out.items()))


def _v2v_link_summary(stats: dict | None) -> dict:
    """The V2V emulator's sums and each ordered pair's counters (from its latest stats)."""
    if stats is None:
        return {"pairs": {}}
    pairs = {f"{p['from']}>{p['to']}": {k: p[k] for k in ("received", "delivered", "dropped", "distance_m")}
             | {"delay_mean_ms": p["delay_ms"].get("mean")} for p in stats.get("pairs", [])}
    return {"total": stats.get("v2v"), "refused": stats.get("refused"), "pairs": pairs}


def _distinct_endpoints(count: int) -> list[str]:
    """``count`` different free loopback TCP endpoints (a port freed a moment ago can come back)."""
    endpoints: list[str] = []
    while len(endpoints) < count:
        if (ep := free_tcp_endpoint()) not in endpoints:
            endpoints.append(ep)
    return endpoints
