"""A run as the plain arrays its report draws (pure): the chaos events as spans, each vehicle's
timeline (modes, latency, misses, RSU delay and clock, target error) and the bird's-eye view
(truth paths, each vehicle's path and the target's fused positions). ``v2i.reports.report_plots``
draws them; ``v2i.reports.run_report`` writes the report.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from v2i.core.frames import base_to_map_points
from v2i.sim.clock import SystemClock, rsu_clock
from v2i.sim.world import World

from v2i.offline.chaos import ChaosEvent, ChaosTimeline
from v2i.scoring.metrics import TargetSeries
from v2i.offline.spec import RunRecord, RunSpec

BEV_STEP_S = 0.1  # truth paths sampled every 0.1 s


@dataclass(frozen=True)
class Span:
    """A chaos event on the timeline (scenario s): a fault from ``from_s`` to ``to_s``, or an
    instantaneous event (``to_s == from_s``: profile switch, clock step, restart)."""

    from_s: float
    to_s: float
    label: str  # ChaosEvent.describe()
    kind: str  # the event's action: outage, delay_spike, loss_burst, bandwidth_cap, kill, profile, ...
    short: str  # a few words for the plot: "+300 ms delay (down)", "link killed", ...

    @property
    def instant(self) -> bool:
        return self.to_s <= self.from_s


def _kind(event: ChaosEvent) -> str:
    return next(n for n in ChaosEvent.model_fields if n != "at_s" and getattr(event, n) is not None)


def short_label(event: ChaosEvent) -> str:
    """A few words naming the event (the plot's label; ``describe`` is the long form)."""
    if event.kill or event.restart:
        return f"{event.kill} killed" if event.kill else f"{event.restart} restarted"
    if event.profile is not None:
        return f"profile {event.profile}"
    if event.rsu_clock_step is not None:
        return f"RSU clock {event.rsu_clock_step.step_ms:+g} ms"
    fault = event.outage or event.delay_spike or event.loss_burst or event.bandwidth_cap
    text = ("outage" if event.outage else f"+{fault.extra_ms:g} ms delay" if event.delay_spike
            else f"loss {fault.loss_probability:.0%}" if event.loss_burst else f"{fault.kbps:g} kbit/s cap")
    return text + {"both": "", "uplink": " (up)", "downlink": " (down)"}[fault.direction]


def chaos_spans(timeline: ChaosTimeline, end_s: float, fired: Sequence[tuple[float, ChaosEvent]] | None = None
                ) -> list[Span]:
    """The spans to shade: each event from when it fired (``fired``: (fired_s, event) as a live
    demo played them; None: every event at its ``at_s``, as offline). An impairment lasts its
    duration; a kill lasts until the next restart of that service fired (else ``end_s``);
    profile switches, clock steps and restarts are instants. Spans end by ``end_s``."""
    played = sorted(fired if fired is not None else [(e.at_s, e) for e in timeline.sorted_events()],
                    key=lambda p: p[0])
    spans = []
    for i, (at_s, event) in enumerate(played):
        fault = event.outage or event.delay_spike or event.loss_burst or event.bandwidth_cap
        if fault is not None:
            to_s = at_s + fault.duration_s
        elif event.kill:
            to_s = next((t for t, e in played[i + 1:] if e.restart == event.kill), end_s)
        else:
            to_s = at_s
        spans.append(Span(round(at_s, 3), round(min(to_s, end_s), 3), event.describe(), _kind(event),
                          short_label(event)))
    return spans


@dataclass(frozen=True)
class RsuTrace:
    """One RSU as one vehicle's OBU saw it, per sample (K,): t_s, delay p50 / p95 and data age
    (ms), clock offset error = estimate - truth (ms) and the estimate's uncertainty (ms); NaN
    where unknown."""

    rsu_id: str
    t_s: np.ndarray
    delay_p50_ms: np.ndarray
    delay_p95_ms: np.ndarray
    age_ms: np.ndarray
    offset_error_ms: np.ndarray
    uncertainty_ms: np.ndarray


@dataclass(frozen=True)
class VehicleTimeline:
    """One vehicle's run as arrays: outputs in cycle order, cycle_s (M,) s, latency_ms (M,)
    publish - capture, modes (M,) names; missed_s (J,) expected cycles with no output by the
    deadline; its RSU traces; the target fused and vehicle-only (``TargetSeries``)."""

    name: str
    deadline_ms: float
    cycle_s: np.ndarray
    latency_ms: np.ndarray
    modes: list[str]
    missed_s: np.ndarray
    rsus: list[RsuTrace]
    target: TargetSeries
    vehicle_only: TargetSeries


def missed_cycles_ns(record: RunRecord, deadline_ms: float) -> np.ndarray:
    """(J,) int64 expected cycle times with no output published by cycle + deadline (the
    misses of ``metrics.deadline_miss_ratio``)."""
    cycle_ns = np.array(record.cycles.cycle_ns, dtype=np.int64)
    publish_ns = np.array(record.cycles.publish_ns, dtype=np.int64)
    on_time = cycle_ns[publish_ns <= cycle_ns + int(deadline_ms * 1e6)]
    expected = np.asarray(record.cycle_times_ns, dtype=np.int64)
    return expected[~np.isin(expected, on_time)]


def rsu_traces(spec: RunSpec, record: RunRecord) -> list[RsuTrace]:
    """The record's link samples per RSU, clock errors against the injected RSU clock (every
    RSU of a run runs the same clock model, as ``build_report`` scores it)."""
    truth = rsu_clock(spec.rsu_config(), SystemClock(), record.start_ns)
    order = [r.id for r in record.world.scenario.rsus]  # the scenario's order; unknown RSUs after
    traces = []
    for s in sorted(record.links.per_rsu(), key=lambda s: order.index(s.rsu_id) if s.rsu_id in order else len(order)):
        true_ns = np.array([truth.offset_at(int(t)) for t in s.t_ns], dtype=float)
        traces.append(RsuTrace(s.rsu_id, (s.t_ns - record.start_ns) * 1e-9, s.delay_p50_ms, s.delay_p95_ms, s.age_ms,
                               (s.offset_ns - true_ns) * 1e-6, s.uncertainty_ns * 1e-6))
    return traces


def vehicle_timeline(spec: RunSpec, name: str, record: RunRecord) -> VehicleTimeline:
    cycle_ns = np.array(record.cycles.cycle_ns, dtype=np.int64)
    publish_ns = np.array(record.cycles.publish_ns, dtype=np.int64)
    order = np.argsort(cycle_ns, kind="stable")
    modes = record.cycles.modes()
    return VehicleTimeline(
        name=name, deadline_ms=spec.deadline_ms, cycle_s=(cycle_ns[order] - record.start_ns) * 1e-9,
        latency_ms=(publish_ns[order] - cycle_ns[order]) * 1e-6, modes=[modes[i] for i in order],
        missed_s=(missed_cycles_ns(record, spec.deadline_ms) - record.start_ns) * 1e-9,
        rsus=rsu_traces(spec, record), target=record.target.series(),
        vehicle_only=record.own_baseline(spec.seed).series())  # the baseline (v2i.offline.baseline)


@dataclass(frozen=True)
class BevVehicle:
    """One vehicle in the bird's-eye view (map, m): its path (T, 2), the target's fused
    positions (K, 2) and their source classes (K,) (``TargetSeries.sources``)."""

    name: str
    path_xy: np.ndarray
    target_xy: np.ndarray
    target_sources: np.ndarray


def bev_vehicle(name: str, world: World, record: RunRecord) -> BevVehicle:
    """The target's fused positions moved to map with the true ego pose of their cycle (the
    frame they were scored in)."""
    series = record.target.series()
    xy = np.array([base_to_map_points(p[None], world.ego_at(t))[0] for p, t in zip(series.out_xy, series.t_s)])
    times = np.arange(0.0, record.duration_s + 1e-9, BEV_STEP_S)
    path = np.array([[world.ego_at(t).x, world.ego_at(t).y] for t in times])
    return BevVehicle(name, path, xy.reshape(-1, 2), series.sources)


def truth_paths(world: World, duration_s: float) -> dict[int, np.ndarray]:
    """Actor id -> (T, 2) map positions every BEV_STEP_S while present (the site view's actors)."""
    paths: dict[int, list] = {}
    for t in np.arange(0.0, duration_s + 1e-9, BEV_STEP_S):
        truth = world.actors_at(float(t))
        for i, xy in zip(truth.ids, truth.xy):
            paths.setdefault(int(i), []).append(xy)
    return {i: np.array(p) for i, p in paths.items()}


def file_name(vehicle: str) -> str:
    """A vehicle name made safe for a file name."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", vehicle)
