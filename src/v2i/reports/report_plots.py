"""The run report's pictures (``v2i.reports.run_report``): matplotlib's object API on the Agg
canvas (no pyplot, no global backend), imported only when a report is written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib import rc_context
from matplotlib.figure import Figure
from matplotlib.patches import Polygon, Wedge
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from obu_service.fusion_mode import MODES

from v2i.reports.run_arrays import BevVehicle, Span, VehicleTimeline
from v2i.offline.spec import first_seen

MODE_COLOURS = {"intra": "#2ca02c", "inter": "#1f77b4", "planning": "#ff7f0e", "vehicle-only": "#8c8c8c"}
SPAN_COLOURS = {"outage": "#d62728", "delay_spike": "#ff7f0e", "loss_burst": "#9467bd", "bandwidth_cap": "#8c564b",
                "kill": "#444444"}
SOURCE_STYLE = {3: ("vehicle + RSU/peer", "#2ca02c"), 2: ("RSU/peer only", "#ff7f0e"), 1: ("vehicle only", "#1f77b4")}
RSU_COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22")
VEHICLE_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")
FONT = {"font.size": 11, "axes.titlesize": 12, "axes.labelsize": 11, "legend.fontsize": 9.5}
LEGEND = {"loc": "upper left", "bbox_to_anchor": (1.005, 1.0), "borderaxespad": 0.0, "frameon": False}
DPI = 110


def _figure(width_in: float, height_in: float) -> Figure:
    return Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")


def _fmt(v, unit: str, nd: int = 1) -> str:
    return "n/a" if v is None else f"{v:.{nd}f} {unit}"


def title_lines(report: dict, vehicle: str | None) -> str:
    """Scenario, profile, seed, driver; then the headline numbers (target, misses, clock)."""
    t, v, c = report["target"], report["vehicle_only"], report["clock_offset_error_ms"]
    who = f" | vehicle {vehicle}" if vehicle else ""
    chaos = f" | chaos {report['chaos']}" if report.get("chaos") else ""
    return (f"{report['scenario']} | profile {report['profile']} | fusion {report['fusion']} ({report['fusion_mode']}) "
            f"| seed {report['seed']} | {report['driver']}, {report['duration_s']:g} s{who}{chaos}\n"
            f"target {first_seen(t['first_detection_distance_m'])} "
            f"(vehicle only: {first_seen(v['first_detection_distance_m'])}), RMSE {_fmt(t['rmse_m'], 'm', 2)} | "
            f"output misses {report['output_deadline_miss_ratio']:.1%}, RSU misses {report['rsu_deadline_miss_ratio']:.1%}"
            f" | clock error p95 {_fmt(c['p95'], 'ms', 2)}")


# --- timeline -----------------------------------------------------------------------------
@rc_context(FONT)
def timeline_png(path: Path, tl: VehicleTimeline, report: dict, spans: list[Span], duration_s: float) -> None:
    """Chaos strip (if any), modes, latency, RSU link, clock error, target error over scenario time."""
    panels = [_modes, _latency, _link, _clock, _target]
    ratios = [0.9, 1.1, 1.3, 1.1, 1.1]
    if spans:
        panels, ratios = [_chaos_strip, *panels], [0.1 + 0.17 * _strip_rows(spans, duration_s), *ratios]
    fig = _figure(14.0, 2.4 * sum(ratios) + 1.0)
    axes = fig.subplots(len(panels), 1, sharex=True, gridspec_kw={"height_ratios": ratios})
    for ax, panel in zip(axes, panels):
        if panel is _chaos_strip:
            panel(ax, spans, duration_s)
            continue
        _shade(ax, spans)
        panel(ax, tl)
        ax.grid(alpha=0.3)
    axes[-1].set_xlim(0.0, duration_s)
    axes[-1].set_xlabel("scenario time (s)")
    fig.suptitle(title_lines(report, tl.name if "vehicles" in report and len(report["vehicles"]) > 1 else None),
                 fontsize=12)
    fig.savefig(path, bbox_inches="tight", pad_inches=0.15)


def _shade(ax, spans: list[Span]) -> None:
    for s in spans:
        colour = SPAN_COLOURS.get(s.kind, "#444444")
        if s.instant:
            ax.axvline(s.from_s, color=colour, lw=1.2, ls=":", alpha=0.8)
        else:
            ax.axvspan(s.from_s, s.to_s, color=colour, alpha=0.10, lw=0)


def _strip_rows(spans: list[Span], duration_s: float) -> int:
    return max(_strip_layout(spans, duration_s).values(), default=0) + 1


def _strip_layout(spans: list[Span], duration_s: float) -> dict[int, int]:
    """Span index -> row, greedily, so that no two labels overlap (a label is ~0.0085 of the
    width per character at 14 in)."""
    ends: list[float] = []
    rows = {}
    for i, s in enumerate(spans):
        label_end = s.from_s + duration_s * 0.0085 * (len(s.short) + 2)
        end = max(s.to_s, label_end)
        row = next((r for r, e in enumerate(ends) if e <= s.from_s), len(ends))
        if row == len(ends):
            ends.append(end)
        else:
            ends[row] = end
        rows[i] = row
    return rows


def _chaos_strip(ax, spans: list[Span], duration_s: float) -> None:
    """Each chaos event as a bar (or a tick for an instant) with its short name, rows without overlap."""
    rows = _strip_layout(spans, duration_s)
    n = max(rows.values(), default=0) + 1
    for i, s in enumerate(spans):
        y, colour = n - 1 - rows[i], SPAN_COLOURS.get(s.kind, "#444444")
        if s.instant:
            ax.plot([s.from_s], [y], marker="|", ms=14, mew=2.5, color=colour)
        else:
            ax.broken_barh([(s.from_s, s.to_s - s.from_s)], (y - 0.32, 0.64), color=colour, alpha=0.35)
        ax.text(s.from_s + duration_s * 0.004, y, s.short, va="center", ha="left", fontsize=9.5)
    ax.set_ylim(-0.6, n - 0.4)
    ax.set_yticks([])
    ax.set_ylabel("chaos", rotation=0, ha="right", va="center")
    for side in ("top", "right", "left"):
        ax.spines[side].set_visible(False)


def _modes(ax, tl: VehicleTimeline) -> None:
    """One row per mode, a bar per cycle in its mode's row and colour."""
    period_s = float(np.median(np.diff(tl.cycle_s))) if len(tl.cycle_s) > 1 else 0.1
    rows = {m: len(MODES) - 1 - k for k, m in enumerate(MODES)}
    for mode in MODES:
        t = tl.cycle_s[[m == mode for m in tl.modes]] if tl.modes else np.zeros(0)
        share = len(t) / max(len(tl.modes), 1)
        ax.broken_barh([(x, period_s) for x in t], (rows[mode] - 0.38, 0.76), color=MODE_COLOURS[mode])
        ax.text(1.005, (rows[mode] + 0.5) / len(MODES), f"{share:.0%}", transform=ax.transAxes, va="center",
                fontsize=9.5, color=MODE_COLOURS[mode])
    ax.set_yticks(list(rows.values()), list(rows))
    ax.set_ylim(-0.6, len(MODES) - 0.4)
    ax.set_title("fusion mode per cycle (share at right)", loc="left")


def _latency(ax, tl: VehicleTimeline) -> None:
    """Publish - capture per output, the deadline, and the expected cycles missed (at the top)."""
    top = max(tl.deadline_ms * 1.3, min(float(np.max(tl.latency_ms, initial=0.0)) * 1.1, tl.deadline_ms * 3))
    shown = np.minimum(tl.latency_ms, top * 0.97)
    ax.plot(tl.cycle_s, shown, ".", ms=4, color="#333333", label="output latency\n(publish - capture)")
    ax.axhline(tl.deadline_ms, color="#d62728", ls="--", lw=1.2, label=f"deadline {tl.deadline_ms:g} ms")
    ax.plot(tl.missed_s, np.full(len(tl.missed_s), top * 0.97), "v", ms=7, color="#d62728",
            label=f"missed cycle ({len(tl.missed_s)})")
    ax.set_ylim(0.0, top)
    ax.set_ylabel("ms")
    ax.set_title("output latency per cycle and deadline misses", loc="left")
    ax.legend(**LEGEND)


def _log_ms(ax) -> None:
    """Log axis labelled 1, 2, 5, 10, 20, 50, ... (plain numbers)."""
    ax.set_yscale("log")
    ax.yaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0), numticks=30))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def _link(ax, tl: VehicleTimeline) -> None:
    """Per RSU: one-way delay p50 (line) and p95 (dashed) over the OBU's window; data age (dots)."""
    if not tl.rsus:
        ax.text(0.5, 0.5, "no RSU link samples", transform=ax.transAxes, ha="center", va="center", color="#777777")
    for k, r in enumerate(tl.rsus):
        colour = RSU_COLOURS[k % len(RSU_COLOURS)]
        ax.plot(r.t_s, r.delay_p50_ms, "-", lw=1.6, color=colour, label=f"{r.rsu_id} delay p50")
        ax.plot(r.t_s, r.delay_p95_ms, "--", lw=1.1, color=colour, label=f"{r.rsu_id} delay p95")
        ax.plot(r.t_s, r.age_ms, ".", ms=3, alpha=0.6, color=colour, label=f"{r.rsu_id} data age at cycle")
    if tl.rsus:
        _log_ms(ax)
    ax.set_ylabel("ms (log)")
    ax.set_title("RSU link: one-way delay (OBU's 10 s window) and age of the RSU data fused", loc="left")
    ax.legend(**LEGEND)


def _clock(ax, tl: VehicleTimeline) -> None:
    """Per RSU: offset estimate - truth (ms) with the estimate's +-uncertainty; symlog beyond 1 ms."""
    for k, r in enumerate(tl.rsus):
        colour = RSU_COLOURS[k % len(RSU_COLOURS)]
        ax.plot(r.t_s, r.offset_error_ms, "-", lw=1.4, color=colour, label=f"{r.rsu_id} estimate - truth")
        for sign in (1.0, -1.0):  # dotted bounds: bands of several RSUs would muddy each other
            ax.plot(r.t_s, r.offset_error_ms + sign * r.uncertainty_ms, ":", lw=1.1, color=colour,
                    label=f"{r.rsu_id} +- uncertainty" if sign > 0 else None)
    ax.axhline(0.0, color="#333333", lw=0.8)
    ax.set_yscale("symlog", linthresh=1.0)
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.set_ylabel("ms (symlog)")
    ax.set_title("clock offset error per RSU (linear within +-1 ms)", loc="left")
    if tl.rsus:
        ax.legend(**LEGEND)


def _target(ax, tl: VehicleTimeline) -> None:
    """Target position error per detected cycle, fused vs the vehicle-only baseline; off-scale points at the top."""
    errors = np.concatenate([tl.target.error_m, tl.vehicle_only.error_m])
    top = max(1.0, float(np.percentile(errors, 99)) * 1.3) if len(errors) else 1.0
    styles = ((tl.vehicle_only, "vehicle-only baseline", {"ms": 6, "mfc": "none", "mec": "#1f77b4", "marker": "s"}),
              (tl.target, "fused output", {"ms": 3.5, "color": "#2ca02c", "marker": "o"}))
    for series, label, style in styles:  # vehicle only hollow and larger: the fused dots show inside
        ax.plot(series.t_s, np.minimum(series.error_m, top * 0.97), ls="none", alpha=0.85,
                label=f"{label} ({len(series.t_s)} cycles)", **style)
    ax.set_ylim(0.0, top)
    ax.set_ylabel("m")
    ax.set_title("target position error |output - truth| per detected cycle", loc="left")
    ax.legend(**LEGEND)


# --- bird's-eye view ------------------------------------------------------------------------
@rc_context(FONT)
def bev_png(path: Path, site, paths: dict[int, np.ndarray], vehicles: list[BevVehicle], report: dict) -> None:
    """Buildings, RSUs with their view, truth paths, vehicle paths, fused target positions (map, m)."""
    (x0, x1), (y0, y1) = bev_limits(site, vehicles)
    fig = _figure(13.0, min(max(8.5 * (y1 - y0) / (x1 - x0) + 1.6, 5.5), 12.0))
    ax = fig.subplots()
    _buildings(ax, site)
    _rsus(ax, site.scenario)
    _truth(ax, site, paths, {v.name for v in vehicles})
    for k, v in enumerate(vehicles):
        _vehicle(ax, v, k, len(vehicles) > 1)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.grid(alpha=0.25)
    ax.legend(**LEGEND)
    fig.suptitle(title_lines(report, None) + "\nbird's-eye view: truth vs the target's fused positions", fontsize=12)
    fig.savefig(path, bbox_inches="tight", pad_inches=0.15)


def _buildings(ax, site) -> None:
    for k, (x, y, length, width, yaw) in enumerate(site.building_boxes):
        c, s = np.cos(yaw), np.sin(yaw)
        corners = np.array([[length, width], [-length, width], [-length, -width], [length, -width]]) / 2.0
        xy = corners @ np.array([[c, s], [-s, c]]) + (x, y)
        ax.add_patch(Polygon(xy, closed=True, color="#d9d9d9", lw=0, label="building" if k == 0 else None))
    for k, poly in enumerate(site.building_polygons):
        label = "building" if k == 0 and not len(site.building_boxes) else None
        ax.add_patch(Polygon(poly, closed=True, color="#d9d9d9", lw=0, label=label))


def _rsus(ax, scenario) -> None:
    for k, rsu in enumerate(scenario.rsus):
        p = rsu.position
        ax.add_patch(Wedge((p.x, p.y), rsu.range_m, rsu.yaw_deg - rsu.fov_deg / 2, rsu.yaw_deg + rsu.fov_deg / 2,
                           color="#ff7f0e", alpha=0.07, lw=0, label="RSU field of view" if k == 0 else None))
        ax.plot([p.x], [p.y], "^", ms=11, color="#ff7f0e", mec="black", label="RSU" if k == 0 else None, zorder=5)
        ax.annotate(rsu.id, (p.x, p.y), xytext=(6, 6), textcoords="offset points", fontsize=10, zorder=6)


def _truth(ax, site, paths: dict[int, np.ndarray], vehicle_names: set[str]) -> None:
    """Truth paths of the actors (not the connected vehicles: drawn with their fused points);
    the target dashed black with its time every 5 s."""
    first = True
    for actor_id, xy in paths.items():
        name = site.actor_names[actor_id]
        if name in vehicle_names:
            continue
        if actor_id == site.target_id:
            ax.plot(xy[:, 0], xy[:, 1], "--", color="black", lw=1.6, label=f"target truth ({name})", zorder=3)
            for t in range(0, len(xy), 50):  # BEV_STEP_S = 0.1: every 5 s
                ax.plot(*xy[t], "k.", ms=6, zorder=3)
                ax.annotate(f"{t // 10} s", xy[t], xytext=(0, -13), textcoords="offset points", ha="center",
                            fontsize=8.5, zorder=3, clip_on=True)
            continue
        moving = np.ptp(xy, axis=0).max() > 0.5
        ax.plot(xy[:, 0], xy[:, 1], "-" if moving else "s", color="#9a9a9a", lw=1.0, ms=4,
                label="other actors (truth)" if first else None, zorder=2)
        first = False


def _vehicle(ax, v: BevVehicle, index: int, several: bool) -> None:
    marker = VEHICLE_MARKERS[index % len(VEHICLE_MARKERS)]
    ax.plot(v.path_xy[:, 0], v.path_xy[:, 1], "-", color="#444444", lw=2.0, zorder=4)
    ax.plot(*v.path_xy[0], marker, ms=11, color="white", mec="black", mew=1.5, zorder=5,
            label=f"vehicle {v.name} (start; path)")
    ax.annotate(v.name, v.path_xy[0], xytext=(8, -12), textcoords="offset points", fontsize=10, zorder=6)
    for code, (label, colour) in SOURCE_STYLE.items():
        rows = v.target_sources == code
        if rows.any():
            who = f"{v.name}: " if several else ""
            ax.scatter(v.target_xy[rows, 0], v.target_xy[rows, 1], s=16, marker=marker, color=colour, alpha=0.75,
                       lw=0, zorder=4, label=f"{who}target output: {label} ({int(rows.sum())})")


def bev_limits(site, vehicles: list[BevVehicle], margin_m: float = 15.0, min_span_m: float = 80.0,
               min_aspect: float = 0.5) -> tuple[tuple[float, float], tuple[float, float]]:
    """(x0, x1), (y0, y1) (m): around the vehicles' paths, the RSUs and the target's outputs with a
    margin, at least ``min_span_m`` wide, neither side below ``min_aspect`` of the other."""
    rsu_xy = np.array([[r.position.x, r.position.y] for r in site.scenario.rsus])
    points = np.vstack([rsu_xy, *(v.path_xy for v in vehicles), *(v.target_xy for v in vehicles)])
    lo, hi = points.min(axis=0) - margin_m, points.max(axis=0) + margin_m
    centre, half = (lo + hi) / 2.0, np.maximum((hi - lo) / 2.0, min_span_m / 2.0)
    half = np.maximum(half, min_aspect * half[::-1])
    return (centre[0] - half[0], centre[0] + half[0]), (centre[1] - half[1], centre[1] + half[1])
