"""What a chaos timeline did to a live run (``v2i chaos run``, ``--kill-link-at``): per played
event when it fired, the emulator's outcome for a link control, and over a fault's window the
cycles published, the fallback sequence of modes and how soon tracking fusion resumed."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from obu_service.fusion_mode import TRACKING_MODES

from v2i.offline.chaos import ChaosEvent, ChaosTimeline
from v2i.scoring.metrics import mode_share
from v2i.offline.spec import RunRecord

MODE_RUNS_SHOWN = 6  # mode changes printed per chaos event


@dataclass
class PlayedEvent:
    """A chaos event as played: when it fired (scenario s) and, for a link event, its control seq."""

    event: ChaosEvent
    fired_s: float
    seq: int | None = None


def window_summary(record: RunRecord, from_s: float, to_s: float) -> dict:
    """Cycles and modes in scenario seconds ``[from_s, to_s)`` (shares, and the sequence of
    modes as ``mode_runs``), and how soon after ``to_s`` tracking fusion (intra or inter)
    resumed (None: not before the run ended); from the record's per-output cycle log."""
    t_s = (np.array(record.cycles.cycle_ns, dtype=np.int64) - record.start_ns) * 1e-9  # (M,) arrival order
    modes = record.cycles.modes()
    during = np.flatnonzero((t_s >= from_s) & (t_s < to_s))
    tracking = np.array([m in TRACKING_MODES for m in modes], dtype=bool).reshape(-1)
    fused_after = np.flatnonzero((t_s >= to_s) & tracking)
    expected_s = (record.cycle_times_ns - record.start_ns) * 1e-9
    return {
        "cycles_published_during": len(during),
        "cycles_expected_during": int(np.count_nonzero((expected_s >= from_s) & (expected_s < to_s))),
        "mode_share_during": mode_share([modes[i] for i in during]),
        "mode_runs_during": mode_runs([(float(t_s[i]), modes[i]) for i in during]),
        "fused_again_after_s": round(float(t_s[fused_after[0]]) - to_s, 3) if len(fused_after) else None,
    }


def mode_runs(cycles: list[tuple[float, str]]) -> list[list]:
    """``[[from_s, mode], ...]``: where the fusion mode changed, in cycle order (the fallback sequence)."""
    runs: list[list] = []
    for t_s, mode in sorted(cycles):
        if not runs or runs[-1][1] != mode:
            runs.append([round(t_s, 3), mode])
    return runs


def outage_summary(record: RunRecord, at_s: float, down_s: float) -> dict:
    """``window_summary`` of a link kill at ``at_s`` for ``down_s`` (``--kill-link-at``)."""
    return {"kill_at_s": at_s, "down_s": down_s, **window_summary(record, at_s, at_s + down_s)}


def chaos_summary(played: list[PlayedEvent], timeline: ChaosTimeline, record: RunRecord,
                  outcomes: dict[int, dict], link_id: str) -> list[dict]:
    """Per played event: what and when; the emulator's outcome for a link control; and for a
    fault with a duration, ``window_summary`` over it."""
    rows = []
    for p in played:
        row: dict = {"at_s": p.event.at_s, "fired_s": p.fired_s, "event": p.event.describe()}
        if p.event.link_control(link_id) is not None:
            outcome = outcomes.get(p.seq) if p.seq is not None else None
            row["link_control"] = ("not sent (emulator down or unreachable)" if p.seq is None else
                                   "not confirmed" if outcome is None else
                                   outcome.get("result") or f"rejected ({outcome['rejected']}): {outcome['error']}")
        window = timeline.fault_window_s(p.event, record.duration_s + 1.0)
        if window is not None:
            row["until_s"] = window[1]
            row.update(window_summary(record, *window))
        rows.append(row)
    return rows


def format_chaos(report: dict) -> str:
    """Human lines for the chaos part of a report (empty without one)."""
    if "chaos_events" not in report:
        return ""
    lines = [f"chaos timeline {report['chaos']}:"]
    for row in report["chaos_events"]:
        line = f"  {row['at_s']:6.1f} s  {row['event']}"
        if "link_control" in row:
            line += f" -> {row['link_control']}"
        if "until_s" in row:
            runs = row["mode_runs_during"]
            modes = " > ".join(f"{mode} {t_s:g} s" for t_s, mode in runs[:MODE_RUNS_SHOWN])
            more = f" > ... ({len(runs) - MODE_RUNS_SHOWN} more changes)" if len(runs) > MODE_RUNS_SHOWN else ""
            again = row["fused_again_after_s"]
            line += (f"\n           until {row['until_s']:g} s: {row['cycles_published_during']}/"
                     f"{row['cycles_expected_during']} cycles published, modes {modes or 'none'}{more}; "
                     f"tracking fusion again {'not before the end' if again is None else f'{again:.2f} s after'}")
        lines.append(line)
    return "\n".join(lines)
