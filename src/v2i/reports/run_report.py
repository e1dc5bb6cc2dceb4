"""``--report DIR``: a run's report as readable pictures (``v2i eval``, ``v2i demo``, ``v2i chaos run``).

From the run's ``RunRecord`` per vehicle (``spec``), its report dict and the chaos events it
played, ``write_run_report`` writes into DIR:

- ``timeline.png`` (one vehicle) or ``timeline-<vehicle>.png`` (a site, one per vehicle):
  panels over scenario time: fusion mode per cycle; output latency per cycle (publish -
  capture) against the deadline, with the missed cycles; per RSU the OBU's one-way delay
  (p50 / p95 over its 10 s window) and the age of the RSU data at each cycle; per RSU the clock
  offset error (estimate - truth) with the estimate's uncertainty; the target's position error,
  fused and vehicle-only. Chaos faults are shaded over every panel and named at the top.
- ``bev.png``: bird's-eye view (map frame, m) of the truth paths, the buildings, the RSUs and
  their fields of view, each vehicle's path and the target's fused positions per cycle
  coloured by their sources (RSU / peer only, fused, vehicle only).
- ``report.json``: the report the run printed.

``run_arrays`` turns the record into plain arrays (pure), ``report_plots`` draws them, this module
writes them.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from v2i.sim.world import World

from v2i.offline.spec import RunRecord, RunSpec
from v2i.reports.run_arrays import Span, bev_vehicle, chaos_spans, file_name, truth_paths, vehicle_timeline


def write_run_report(folder: Path, report: dict, spec: RunSpec, vehicles: Sequence[tuple[str, World, RunRecord]],
                     spans: Sequence[Span] = ()) -> list[Path]:
    """Write the timeline(s), the BEV and ``report.json`` into ``folder`` (made if missing);
    the paths written. ``vehicles``: (name, world, record), the ego first."""
    from v2i.reports import report_plots

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, _, record in vehicles:
        own = report if len(vehicles) == 1 else {**report, **report["vehicles"][name]}
        path = folder / ("timeline.png" if len(vehicles) == 1 else f"timeline-{file_name(name)}.png")
        report_plots.timeline_png(path, vehicle_timeline(spec, name, record), own, list(spans), record.duration_s)
        written.append(path)
    world, duration_s = vehicles[0][1], vehicles[0][2].duration_s
    site = World(world.scenario, site=True)
    bev = [bev_vehicle(name, w, r) for name, w, r in vehicles]
    path = folder / "bev.png"
    report_plots.bev_png(path, site, truth_paths(site, duration_s), bev, report)
    written.append(path)
    path = folder / "report.json"
    path.write_text(json.dumps(report, indent=2) + "\n")
    return written + [path]


def write_offline_report(folder: Path, report: dict, run) -> list[Path]:
    """``write_run_report`` of an ``OfflineRun`` (made with ``link_series=True`` for the RSU panels);
    its chaos events at their scheduled times."""
    spans = chaos_spans(run.chaos, run.duration_s) if run.chaos is not None else []
    return write_run_report(folder, report, run.spec, [(v.name, v.world, v.record) for v in run.vehicles], spans)


def write_demo_report(folder: Path, report: dict, demo) -> list[Path]:
    """``write_run_report`` of a finished live demo: a ``SiteDemo`` (every vehicle's record) or a
    ``Demo`` (its chaos events at the times they fired)."""
    if hasattr(demo, "records"):
        vehicles = [(name, demo.worlds[name], demo.records[name]) for name in demo.vehicle_ids]
        return write_run_report(folder, report, demo.spec, vehicles)
    fired = [(p.fired_s, p.event) for p in demo.played]
    spans = chaos_spans(demo.chaos, demo.duration_s, fired) if demo.chaos is not None else []
    name = demo.spec.obu_config().vehicle_id
    return write_run_report(folder, report, demo.spec, [(name, demo.world, demo.record)], spans)
