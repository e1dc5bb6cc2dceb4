"""What a run is (shared by ``v2i eval`` and ``v2i demo``) and how its report is built."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

from schemas.messages import SOURCE_VEHICLE, FusedObjectList, PredictionList
from obu_service.config import ObuConfig
from rsu_service.config import RsuConfig
from sim.clock import SystemClock
from sim.world import World

from .metrics import (clock_errors, deadline_miss_ratio, detection_scores, displacement_error_m, mode_share,
                      score_target)

# Offline runs start at a fixed epoch (2026-01-01T00:00:00Z) so that reports are reproducible.
EVAL_EPOCH_NS = 1_767_225_600 * 10**9


@dataclass(frozen=True)
class RunSpec:
    scenario: str = "red-light-runner"
    profile: str = "lte-v2x"
    fusion: str = "kf"
    compensation: str = "predict"
    fusion_mode: str = "adaptive"
    inter_max_age_s: float = 0.6  # inter-frame fusion uses RSU data up to this old (seed 003)
    seed: int = 0
    duration_s: float | None = None  # default: the scenario's
    rsu_clock_offset_ms: float = 0.0
    rsu_clock_drift_ppm: float = 0.0
    rsu_clock_step_ms: float = 0.0
    rsu_clock_step_at_s: float | None = None
    deadline_ms: float = 100.0

    def rsu_config(self, **fields) -> RsuConfig:
        """The RSU service configuration this run implies (its clock is the injected truth)."""
        return RsuConfig(clock_offset_ms=self.rsu_clock_offset_ms, clock_drift_ppm=self.rsu_clock_drift_ppm,
                         clock_step_ms=self.rsu_clock_step_ms, clock_step_at_s=self.rsu_clock_step_at_s,
                         seed=self.seed, scenario=self.scenario, predict_ahead=self.compensation == "track-predict",
                         **fields)

    def obu_config(self, **fields) -> ObuConfig:
        """The OBU service configuration this run implies."""
        return ObuConfig(fusion=self.fusion, compensation=self.compensation, fusion_mode=self.fusion_mode,
                         inter_max_age_s=self.inter_max_age_s, deadline_ms=self.deadline_ms, seed=self.seed,
                         scenario=self.scenario, **fields)


@dataclass
class RunRecord:
    """What a run produced, whichever driver ran it (times in the OBU = true clock)."""

    start_ns: int
    duration_s: float
    cycle_times_ns: Sequence[int]
    outputs: list[FusedObjectList] = field(default_factory=list)
    # (t_ns, estimated theta_ns, naive theta_ns, estimated drift ppm)
    offset_samples: list[tuple[int, int, int, float]] = field(default_factory=list)
    planning: list[PredictionList] = field(default_factory=list)  # paths handed to the planner (OBU clock)
    rsu_messages: int = 0
    covered_cycles: int = 0  # the OBU's own count: cycles with an RSU heard recently
    rsu_deadline_misses: int = 0

    def add_output(self, output: FusedObjectList, planning: PredictionList | None) -> None:
        self.outputs.append(output)
        if planning is not None:
            self.planning.append(planning)


def build_report(spec: RunSpec, world: World, record: RunRecord, driver: str) -> dict:
    """The metrics JSON: same keys from ``eval`` and ``demo``."""
    truth_clock = spec.rsu_config().clock(SystemClock(), record.start_ns)
    fused = score_target(world, record.outputs, record.start_ns)
    own = score_target(world, record.outputs, record.start_ns, sources_mask=SOURCE_VEHICLE)
    step_ns = None if spec.rsu_clock_step_at_s is None else record.start_ns + round(spec.rsu_clock_step_at_s * 1e9)
    return {
        "driver": driver,
        **{k: v for k, v in asdict(spec).items() if k not in ("duration_s",)},
        "duration_s": record.duration_s,
        "cycles": len(record.cycle_times_ns),
        "outputs": len(record.outputs),
        "output_deadline_miss_ratio": round(deadline_miss_ratio(record.cycle_times_ns, record.outputs, spec.deadline_ms), 4),
        "rsu_deadline_miss_ratio": round(record.rsu_deadline_misses / max(record.covered_cycles, 1), 4),
        "mode_share": mode_share([m.mode for m in record.outputs]),
        "displacement_error_m": displacement_error_m(world, record.planning, record.start_ns),
        "planning_handoffs": len(record.planning),
        "rsu_messages_received": record.rsu_messages,
        "target": fused.as_dict(),
        "vehicle_only": own.as_dict(),
        **clock_errors(record.offset_samples, truth_clock, record.start_ns, step_ns),
        **detection_scores(world, record.outputs, record.start_ns),
    }


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
        f"  target ({report['scenario']}) first seen at {_m(fd)} with V2I vs {_m(vd)} vehicle-only{gain}",
        f"  target: mean BEV IoU {_f(t['mean_bev_iou'])}, RMSE {_m(t['rmse_m'])} over {t['detected_cycles']} cycles",
        f"  deadline misses: output {report['output_deadline_miss_ratio']:.1%}, RSU {report['rsu_deadline_miss_ratio']:.1%}"
        f"; modes: {share}; RSU lists received {report['rsu_messages_received']}",
        f"  clock offset error p50 {_f(c['p50'])} ms, p95 {_f(c['p95'])} ms, max {_f(c['max'])} ms "
        f"(naive p95 {_f(report['clock_offset_error_naive_ms']['p95'])} ms); "
        f"drift error {_f(report['clock_drift_error_ppm'])} ppm",
    ]
    if report["displacement_error_m"] is not None:
        lines.append(f"  planning: {report['planning_handoffs']} hand-offs, displacement error "
                     f"{report['displacement_error_m']:.2f} m")
    return "\n".join(lines)


def _m(v) -> str:
    return "never" if v is None else f"{v:.1f} m"


def _f(v) -> str:
    return "n/a" if v is None else f"{v:.3f}"
