"""What a run is (shared by ``v2i eval`` and ``v2i demo``) and how its report is built."""

from __future__ import annotations

from array import array
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from v2i.core.objects import ObjectArray
from schemas.messages import FusedObjectList, ObuMetrics, PredictionList
from obu_service.config import ObuConfig
from v2i.perception.scoring import PerceptionTally
from rsu_service.config import RsuConfig
from v2i.sim.clock import SystemClock, rsu_clock
from v2i.sim.world import World

from v2i.scoring.link_series import LinkSeries
from v2i.scoring.metrics import (FUSED, PLANNED, CycleFrame, CycleLog, DetectionTally, DisplacementTally, TargetTally,
                                 clock_errors, deadline_miss_ratio, mode_share)
from v2i.offline.baseline import OwnBaseline, own_baseline
from obu_service.source import OwnFrame

# Offline runs start at a fixed epoch (2026-01-01T00:00:00Z) so that reports are reproducible.
EVAL_EPOCH_NS = 1_767_225_600 * 10**9


@dataclass(frozen=True)
class RunSpec:
    scenario: str = "red-light-runner"
    profile: str = "lte-v2x"
    fusion: str = "kf"
    compensation: str = "predict"
    fusion_mode: str = "adaptive"
    inter_max_age_s: float = 0.6  # inter-frame fusion uses RSU data up to this old (IAAD, Liu et al.)
    seed: int = 0
    duration_s: float | None = None  # default: the scenario's
    rsu_clock_offset_ms: float = 0.0
    rsu_clock_drift_ppm: float = 0.0
    rsu_clock_step_ms: float = 0.0
    rsu_clock_step_at_s: float | None = None
    deadline_ms: float = 100.0
    rsu_source: str = "sim"  # sim (noise model) or camera (rendered, detector, calibration)
    v2v: bool | None = None  # vehicles share lists (V2V): None as the scenario says, True / False on / off
    wire: str = "v2i"  # RSU object list encoding: v2i, cpm or sdsm (schemas.list_wire)
    cpm_rules: bool = False  # with wire cpm: TS 103 324 generation rules and segmentation (rsu_service.cpm_rules)
    security: str | None = None  # RSUs sign and the OBU verifies: strict, permissive or off; None: nothing signed

    def rsu_config(self, **fields) -> RsuConfig:
        """The RSU service configuration this run implies (its clock is the injected truth)."""
        return RsuConfig(clock_offset_ms=self.rsu_clock_offset_ms, clock_drift_ppm=self.rsu_clock_drift_ppm,
                         clock_step_ms=self.rsu_clock_step_ms, clock_step_at_s=self.rsu_clock_step_at_s,
                         seed=self.seed, scenario=self.scenario, predict_ahead=self.compensation == "track-predict",
                         source=self.rsu_source, wire=self.wire, cpm_rules=self.cpm_rules, **fields)

    def obu_config(self, **fields) -> ObuConfig:
        """The OBU service configuration this run implies."""
        return ObuConfig(fusion=self.fusion, compensation=self.compensation, fusion_mode=self.fusion_mode,
                         inter_max_age_s=self.inter_max_age_s, deadline_ms=self.deadline_ms, seed=self.seed,
                         scenario=self.scenario, **fields)


class RunRecord:
    """What a run produced, whichever driver ran it, scored as each output arrives (times in
    the OBU = true clock). ``v2i eval`` and ``v2i demo`` feed it; ``build_report`` reads it.

    Nothing grows with the run but compact per-cycle numbers: per output 17 bytes
    (``CycleLog``) and 10 bytes per predicted object in range (``CenterDistanceAp``), 56
    bytes per cycle the target is detected (twice: fused and the vehicle-only baseline), 34 bytes
    per clock-offset sample (one per synced RSU per cycle), 19 per RSU a cycle used; plus counts
    per track id for IDF1 (twice) and the baseline tracker's tracks. For the run report
    (``v2i.reports.run_report``): 17 more bytes per cycle the target is detected (twice), and
    41 bytes per RSU per OBU metrics sample (one per cycle; ``link_series.LinkSeries``).
    """

    def __init__(self, world: World, start_ns: int, duration_s: float, cycle_times_ns: Sequence[int] = ()):
        self.world, self.start_ns, self.duration_s = world, start_ns, duration_s
        self.cycle_times_ns = np.asarray(cycle_times_ns, dtype=np.int64)  # expected cycles (K,) ns
        self.cycles = CycleLog()
        self.detection = DetectionTally()
        self.target = TargetTally(world.target_id, mot=self.detection.mot)  # id switches: the run's MotTally's
        # the vehicle-only baseline (v2i.offline.baseline): the own sensors through a fixed own-only tracker,
        # fed by the driver (add_own_frame) or, when it fed none, computed by build_report
        self.baseline: OwnBaseline | None = None
        self._computed_baseline: TargetTally | None = None
        self.displacement = DisplacementTally(world, start_ns)
        self.planning_handoffs = 0  # paths handed to the planner (OBU clock)
        # clock-offset samples: t_ns, estimated theta_ns, naive theta_ns, estimated drift ppm, RSU index
        self._offsets = (array("q"), array("q"), array("q"), array("d"), array("h"))
        self.rsu_ids: list[str] = []  # RSU index -> id, in order of first sample
        # the clock of the cycles that used RSU data: cycle t_ns, theta_ns at it, RSU index, FUSED or PLANNED
        self._used_clock = (array("q"), array("q"), array("h"), array("b"))
        self.clock_steps: dict[str, int] | None = None  # RSU id -> steps its estimator confirmed (None: unknown)
        self.perception = PerceptionTally()  # the RSU's raw detections against the truth it could see
        # live runs: each service's latest per-stage latency ("rsu", "link", "obu": {stage: {count, p50, p95,
        # p99}} in ms, v2i.telemetry.latency); offline none (its clock is simulated)
        self.latency_ms: dict[str, dict] = {}
        self.rsu_perception: dict | None = None  # or the RSU's own scores (live: from its metrics)
        self.rsu_messages = 0
        self.rejected: dict[str, int] = {}  # the OBU's refused inputs by reason (codec, admission, security_*)
        self.mode_reasons: dict[str, int] = {}  # the OBU's outputs by mode_reason (obu_service.fusion_mode)
        self.covered_cycles = 0  # the OBU's own count: cycles with an RSU heard recently
        self.obu_cycles: int | None = None  # live: the OBU's own count of cycles published (None: no metrics)
        self.obu_output_deadline_misses = 0  # live: the OBU's own count of those published late
        self.rsu_deadline_misses = 0
        self.crowded_out_cycles = 0  # live: cycles that fell back while the OBU's intake refused genuine input
        self.rsu_lists: dict[str, dict[str, int | None]] = {}  # per RSU: lists "accepted", "sent" (numbered)
        self.links = LinkSeries()  # per-cycle RSU link samples (live: ObuMetrics; offline: link_series=True)

    def add_output(self, output: FusedObjectList, planning: PredictionList | None = None,
                   truth: tuple[float, ObjectArray] | None = None) -> None:
        """One published cycle (and the RSU paths it handed to the planner, if any); ``truth``:
        (t_s, the truth in base_link) derived at the cycle's capture (``CycleFrame.of``)."""
        self.cycles.add(output)
        frame = CycleFrame.of(self.world, output, self.start_ns, truth)
        for tally in (self.target, self.detection):
            tally.add(frame)
        if planning is not None:
            self.add_planning(planning)

    def add_planning(self, planning: PredictionList) -> None:
        self.planning_handoffs += 1
        self.displacement.add(planning)

    def add_own_frame(self, frame: OwnFrame, truth: tuple[float, ObjectArray] | None = None, site=None) -> None:
        """One of the vehicle's own frames into the vehicle-only baseline (every cycle, whatever the OBU did
        with it); ``truth`` as in ``add_output``; ``site``: the scenario's (``site_of``) on the first frame."""
        if self.baseline is None:
            self.baseline = OwnBaseline(self.world, self.start_ns, site)
        self.baseline.add(frame, truth)

    @property
    def vehicle_target(self) -> TargetTally:
        """The vehicle-only baseline's target tally fed so far (``own_baseline`` computes it when none was fed)."""
        if self.baseline is not None:
            return self.baseline.tally
        return self._computed_baseline or TargetTally(self.world.target_id)

    def _rsu_index(self, rsu_id: str) -> int:
        if rsu_id not in self.rsu_ids:
            self.rsu_ids.append(rsu_id)
        return self.rsu_ids.index(rsu_id)

    def add_offset_sample(self, t_ns: int, theta_ns: int, naive_theta_ns: int, drift_ppm: float,
                          rsu_id: str = "") -> None:
        """One RSU's clock estimate at OBU time t_ns (scored against that RSU's true clock)."""
        for column, value in zip(self._offsets, (t_ns, theta_ns, naive_theta_ns, drift_ppm, self._rsu_index(rsu_id))):
            column.append(value)

    def add_used_clock(self, cycle_ns: int, rsu_id: str, theta_ns: int, planned: bool = False) -> None:
        """A cycle fused (intra, inter) the RSU's data, or placed its paths (``planned``), through the
        offset estimate theta_ns at the cycle time."""
        values = (cycle_ns, theta_ns, self._rsu_index(rsu_id), PLANNED if planned else FUSED)
        for column, value in zip(self._used_clock, values):
            column.append(value)

    def add_obu_metrics(self, metrics: ObuMetrics) -> None:
        """The OBU's metrics message (the live driver): its clock-offset samples; its counts
        replace the record's (the last message holds the run's totals)."""
        # the RSUs the last cycle used (ObuPipeline.last_rsu_inputs); from a producer that does not say (None),
        # every synced RSU of a cycle in a mode that uses RSU data
        used = metrics.rsu_inputs
        for r in metrics.rsus:
            if None not in (r.clock_offset_ns, r.clock_offset_naive_ns, r.clock_drift_ppm):
                self.add_offset_sample(metrics.t_ns, r.clock_offset_ns, r.clock_offset_naive_ns, r.clock_drift_ppm,
                                       r.rsu_id)
                if (r.rsu_id in used) if used is not None else metrics.mode in ("intra", "inter", "planning"):
                    self.add_used_clock(metrics.t_ns, r.rsu_id, r.clock_offset_ns, planned=metrics.mode == "planning")
            self.clock_steps = {**(self.clock_steps or {}), r.rsu_id: r.clock_steps}  # the latest: the run's so far
        self.rsu_messages = sum(r.messages_accepted for r in metrics.rsus)  # every RSU's, as offline
        self.covered_cycles, self.rsu_deadline_misses = metrics.covered_cycles, metrics.rsu_deadline_misses
        self.crowded_out_cycles, self.rsu_lists = metrics.crowded_out_cycles, rsu_lists(metrics)
        self.obu_cycles, self.obu_output_deadline_misses = metrics.cycles, metrics.output_deadline_misses
        self.rejected = dict(metrics.rejected)
        self.mode_reasons = dict(metrics.mode_reasons)
        if metrics.latency_ms:
            self.latency_ms["obu"] = {stage: q.model_dump() for stage, q in metrics.latency_ms.items()}
        self.links.add(metrics.t_ns, metrics.rsus)

    def offset_samples(self) -> np.ndarray:
        """(K, 5) float64: t_ns, theta_ns, naive theta_ns, drift ppm, RSU index (``rsu_ids``)."""
        return np.column_stack([np.array(c, dtype=float) for c in self._offsets]).reshape(-1, 5)

    def used_clock(self) -> np.ndarray:
        """(F, 4) float64: cycle t_ns, theta_ns, RSU index, FUSED or PLANNED (``add_used_clock``)."""
        return np.column_stack([np.array(c, dtype=float) for c in self._used_clock]).reshape(-1, 4)

    def own_baseline(self, seed: int) -> TargetTally:
        """The vehicle-only baseline's tally: the one fed frame by frame, else computed from the scenario,
        ``seed``, the start and the cycle times (``v2i.offline.baseline.own_baseline``)."""
        if self.baseline is not None:
            return self.baseline.tally
        if self._computed_baseline is None:  # computed once (build_report, the run report's arrays)
            self._computed_baseline = own_baseline(self.world, seed, self.start_ns, self.cycle_times_ns)
        return self._computed_baseline


def rsu_lists(metrics: ObuMetrics) -> dict[str, dict[str, int | None]]:
    """Per RSU id: the lists the OBU ``accepted`` and those the RSU numbered (``sent``, None: not known)."""
    return {r.rsu_id: {"accepted": r.messages_accepted, "sent": r.messages_sent} for r in metrics.rsus}


def build_report(spec: RunSpec, world: World, record: RunRecord, driver: str) -> dict:
    """The metrics JSON: same keys from ``eval`` and ``demo``. ``world``: the one the record
    scored its outputs against (a different one is an error: the scores would not be its)."""
    if record.world is not world:
        raise ValueError("build_report: the record was scored against another world")
    # every RSU's true clock, by the record's RSU index (the sim gives each the same model: spec.rsu_config())
    truth_clocks = [rsu_clock(spec.rsu_config(rsu_id=rid or "rsu"), SystemClock(), record.start_ns)
                    for rid in record.rsu_ids]
    step_ns = None if spec.rsu_clock_step_at_s is None else record.start_ns + round(spec.rsu_clock_step_at_s * 1e9)
    cycles = record.cycles
    return {
        "driver": driver,
        **{k: v for k, v in asdict(spec).items() if k not in ("duration_s",) and (k, v) not in _UNSAID},
        "duration_s": record.duration_s,
        "cycles": len(record.cycle_times_ns),
        "outputs": len(cycles),
        "output_deadline_miss_ratio": round(deadline_miss_ratio(record.cycle_times_ns, cycles.cycle_ns, cycles.publish_ns,
                                                                spec.deadline_ms), 4),
        "rsu_deadline_miss_ratio": round(record.rsu_deadline_misses / max(record.covered_cycles, 1), 4),
        "mode_share": mode_share(cycles.modes()),
        "displacement_error_m": record.displacement.value(),
        "planning_handoffs": record.planning_handoffs,
        "rsu_messages_received": record.rsu_messages,
        "rsu_lists_accepted": dict(sorted(record.rsu_lists.items())),
        "crowded_out_cycles": record.crowded_out_cycles,
        "obu_rejected": dict(sorted(record.rejected.items())),
        "mode_reasons": dict(sorted(record.mode_reasons.items())),
        "target": record.target.score().as_dict(),
        "vehicle_only": record.own_baseline(spec.seed).score().as_dict(),
        **clock_errors(record.offset_samples(), truth_clocks, record.start_ns, step_ns, record.used_clock(),
                       record.clock_steps, record.rsu_ids),
        **record.detection.scores(),
        "rsu_perception": record.rsu_perception or record.perception.scores(),
        "latency_ms": dict(record.latency_ms),
    }


_UNSAID = {("cpm_rules", False)}  # options a report names only when on (reports without them stay as they were)
_RUN_KEYS = ("driver", *RunSpec.__dataclass_fields__)  # what describes the run, not one vehicle's scores


def site_report(spec: RunSpec, vehicles: Sequence[tuple[str, World, RunRecord]], rsus: dict[str, dict],
                driver: str) -> dict:
    """The ego's (first vehicle's) ``build_report``, plus ``vehicles``: each vehicle's scores
    by name (the same keys without the run's description), and ``rsus``: each RSU's
    perception scores by id."""
    reports = {name: build_report(spec, world, record, driver) for name, world, record in vehicles}
    ego = reports[vehicles[0][0]]
    return {**ego,
            "vehicles": {name: {k: v for k, v in r.items() if k not in _RUN_KEYS} for name, r in reports.items()},
            "rsus": rsus}


def summary(report: dict) -> str:
    """A short human summary of a report."""
    t, v, c = report["target"], report["vehicle_only"], report["clock_offset_error_ms"]
    fd, vd = t["first_detection_distance_m"], v["first_detection_distance_m"]
    gain = f" ({fd / vd:.1f}x farther)" if fd and vd else ""
    share = ", ".join(f"{m} {s:.0%}" for m, s in report["mode_share"].items())
    lines = [
        f"{report['scenario']} | profile {report['profile']} | fusion {report['fusion']} "
        f"({report['compensation']}, mode {report['fusion_mode']}) | seed {report['seed']} "
        f"| {report['duration_s']:.1f} s, {report['cycles']} cycles ({report['driver']})",
        f"  target ({report['scenario']}): {first_seen(fd)} with V2I, {first_seen(vd)} vehicle-only{gain}",
        f"  target: {_accuracy(t)}",
        f"  deadline misses: output {report['output_deadline_miss_ratio']:.1%}{_own_count(report)}, "
        f"RSU {report['rsu_deadline_miss_ratio']:.1%}{_crowded(report)}; modes: {share}; RSU lists received "
        f"{report['rsu_messages_received']}{_sent(report)}",
        f"  clock offset error p50 {_f(c['p50'])} ms, p95 {_f(c['p95'])} ms, max {_f(c['max'])} ms "
        f"(naive p95 {_f(report['clock_offset_error_naive_ms']['p95'])} ms); "
        f"drift error {_f(report['clock_drift_error_ppm'])} ppm",
    ]
    if "clock_error_when_fused_max_ms" in report:  # (reports written before these figures have none)
        lines.append(f"  clock when used: fused max {_ms(report['clock_error_when_fused_max_ms'])}, planning max "
                     f"{_ms(report['clock_error_when_planning_max_ms'])}; steps detected "
                     f"{_n(report['clock_steps_detected'])}" + _step_text(report))
    p = report["rsu_perception"]
    if p["frames"]:
        e, ms = p["mean_error_m"], p["detector_ms"]
        lines.append(f"  RSU perception ({report['rsu_source']}): recall {_f(p['recall'])}, precision {_f(p['precision'])}, "
                     f"mean error {' / '.join(_f(v) for v in e.values())} m ({' / '.join(e)})"
                     + (f"; detector p50 {ms['p50']:.1f} ms, p99 {ms['p99']:.1f} ms" if ms else ""))
    for name, v in report.get("vehicles", {}).items() if len(report.get("vehicles", {})) > 1 else ():
        t = v["target"]
        lines.append(f"  vehicle {name}: target {first_seen(t['first_detection_distance_m'])} "
                     f"(vehicle-only: {first_seen(v['vehicle_only']['first_detection_distance_m'])}), "
                     f"RMSE {_rmse(t['rmse_m'])}, "
                     f"{t['track_ids']} track id(s), {t['id_switches']} switch(es); output misses "
                     f"{v['output_deadline_miss_ratio']:.1%}")
    if report["displacement_error_m"] is not None:
        lines.append(f"  planning: {report['planning_handoffs']} hand-offs, displacement error "
                     f"{report['displacement_error_m']:.2f} m")
    return "\n".join(lines)


def _step_text(report: dict) -> str:
    """With an injected step: its window's errors and the recovery (empty without one)."""
    if "clock_step_recovery_s" not in report:
        return ""
    w, rec = report["clock_offset_error_step_window_ms"], report["clock_step_recovery_s"]
    return (f"; step window p95 {_ms(w['p95'])}, max {_ms(w['max'])}; recovered "
            + ("never (the run ended outside the pre-step error)" if rec is None else f"after {rec:.2f} s"))


def _ms(v) -> str:
    """A figure in ms, or n/a (none: no cycle of that kind, no sample)."""
    return "n/a" if v is None else f"{v:.3f} ms"


def _n(v) -> str:
    return "n/a" if v is None else str(v)


def _own_count(report: dict) -> str:
    """A live run's OBU's own count beside the output misses (empty offline or without its metrics)."""
    own = next(iter((report.get("obu_output_deadline_misses") or {}).values()), None)
    return "" if own is None else f" (the OBU's own count: {own['misses']} of {own['cycles']} late)"


def _crowded(report: dict) -> str:
    """The cycles that fell back while genuine input was crowded out, when any (live only)."""
    n = report.get("crowded_out_cycles")
    return f", {n} cycles crowded out" if n else ""


def _sent(report: dict) -> str:
    """Lists accepted of those the RSUs sent (by their numbering), when some were not."""
    lists = (report.get("rsu_lists_accepted") or {}).values()
    sent = [r["sent"] for r in lists if r["sent"] is not None]
    accepted = sum(r["accepted"] for r in lists if r["sent"] is not None)
    return f", accepted {accepted} of {sum(sent)} sent" if sent and sum(sent) > accepted else ""


def first_seen(distance_m: float | None) -> str:
    """Where the target was first detected (its distance from the ego), or that it was not."""
    return "not seen" if distance_m is None else f"first seen at {distance_m:.1f} m"


def _accuracy(target: dict) -> str:
    """The target's BEV IoU and RMSE over the cycles it was detected in, or that there were none."""
    if not target["detected_cycles"]:
        return "not detected in any cycle (no IoU or RMSE)"
    return (f"mean BEV IoU {_f(target['mean_bev_iou'])}, RMSE {_rmse(target['rmse_m'])} "
            f"over {target['detected_cycles']} cycles")


def _rmse(rmse_m: float | None) -> str:
    return "n/a" if rmse_m is None else f"{rmse_m:.2f} m"


def _f(v) -> str:
    return "n/a" if v is None else f"{v:.3f}"
