"""Accounting and table of ``v2i attack`` (pure): what each attack kind did to the OBU and the link.

The OBU's ``ObuMetrics.rejected`` and the emulator's ``control.rejected`` are cumulative counters;
each kind runs in its own phase, so the counters' growth over the phase (plus a settling time)
is what that kind caused. Labels: ``security_<reason>`` = dropped by the verifier,
``security_accepted_<reason>`` = failed but let through (``permissive``), anything else = a
later refusal (e.g. admission's ``duplicate`` for a replay the verifier let through).
"""

from __future__ import annotations

from collections.abc import Mapping

from v2i.adversary.attack_messages import INTENDED

DROP, ACCEPT = "security_", "security_accepted_"


def counter_delta(after: Mapping[str, int], before: Mapping[str, int]) -> dict[str, int]:
    """The labels that grew from ``before`` to ``after``, by how much."""
    return {k: v - before.get(k, 0) for k, v in sorted(after.items()) if v > before.get(k, 0)}


def split_labels(delta: Mapping[str, int]) -> tuple[dict[str, int], dict[str, int], dict[str, int]]:
    """(dropped by reason, accepted-but-failing by reason, other refusals) of OBU rejection labels."""
    dropped, accepted, other = {}, {}, {}
    for label, n in delta.items():
        if label.startswith(ACCEPT):
            accepted[label[len(ACCEPT):]] = n
        elif label.startswith(DROP):
            dropped[label[len(DROP):]] = n
        else:
            other[label] = n
    return dropped, accepted, other


def kind_row(kind: str, sent: Mapping[str, int], obu_delta: Mapping[str, int], ghost_outputs: int,
             ghost_objects: int, outputs: int, window_s: float, control_delta: Mapping[str, int] | None = None,
             control_applied: int | None = None, clock_shift_ms: float | None = None) -> dict:
    """One kind's line of the report. ``sent``: by variant; ``obu_delta``: OBU labels grown in the
    phase; ``control_delta`` / ``control_applied``: the emulator's (kind ``control``)."""
    if kind == "control":
        dropped, accepted, other = dict(control_delta or {}), {}, {}
    else:
        dropped, accepted, other = split_labels(obu_delta)
    total = sum(sent.values())
    intended = sum(dropped.get(r, 0) for r in INTENDED[kind])
    row = {"sent": total, "variants": dict(sent), "rejected": dropped, "rejected_total": sum(dropped.values()),
           "rejected_as_intended": intended, "accepted": accepted, "other_refusals": other,
           "ghost_outputs": ghost_outputs, "ghost_objects": ghost_objects, "outputs": outputs,
           "window_s": round(window_s, 2)}
    if control_applied is not None:
        row["control_applied"] = control_applied
    if clock_shift_ms is not None:
        row["clock_shift_max_ms"] = round(clock_shift_ms, 3)
    return row


def got_through(report: dict) -> list[str]:
    """What of the attack got through (empty: everything was stopped)."""
    notes = []
    for kind, row in report["kinds"].items():
        if row["accepted"]:
            notes.append(f"{kind}: {sum(row['accepted'].values())} of {row['sent']} failed verification and were accepted")
        elif row["rejected_total"] + sum(row["other_refusals"].values()) < row["sent"]:
            notes.append(f"{kind}: {row['sent'] - row['rejected_total']} of {row['sent']} not rejected by the verifier")
        if row["ghost_outputs"]:
            notes.append(f"{kind}: a ghost in {row['ghost_outputs']} fused outputs")
        if row.get("control_applied"):
            notes.append(f"control: {row['control_applied']} applied by the link emulator")
        if abs(row.get("clock_shift_max_ms") or 0.0) >= 100.0:
            notes.append(f"time: the OBU's clock estimate moved {row['clock_shift_max_ms']} ms")
    misses = report["genuine"].get("output_deadline_misses")
    if misses:
        notes.append(f"{misses} output deadline misses during the attack")
    return notes


def _reasons(counts: Mapping[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items(), key=lambda kv: -kv[1])) or "-"


def _effect(kind: str, row: dict) -> str:
    if kind == "control":
        return f"applied by the emulator: {row.get('control_applied', '?')}"
    if kind == "time":
        shift = row.get("clock_shift_max_ms")
        return f"clock estimate moved at most {'?' if shift is None else f'{shift:g}'} ms"
    if kind == "replayed":
        return f"(genuine content) outputs {row['outputs']}"
    return f"ghost in {row['ghost_outputs']} of {row['outputs']} outputs"


def format_report(report: dict) -> str:
    """The human table: per kind sent, rejected by reason, accepted under permissive, what reached
    the output; then the genuine traffic and the ghost rule's false positives."""
    lines = [f"v2i attack on {report['rsu_id']} -> OBU {report['vehicle_id']}: {report['count']} per kind at "
             f"{report['rate_hz']:g}/s",
             f"  {'kind':<10}{'sent':>6}{'rejected':>9}  {'rejected by reason':<44}{'accepted (permissive)':<32}"
             f"{'other refusals':<24}reached the output"]
    for kind, row in report["kinds"].items():
        lines.append(f"  {kind:<10}{row['sent']:>6}{row['rejected_total']:>9}  {_reasons(row['rejected']):<44}"
                     f"{_reasons(row['accepted']):<32}{_reasons(row['other_refusals']):<24}{_effect(kind, row)}")
    g, b = report["genuine"], report["baseline"]
    lines += [
        f"  genuine during the attack ({g['window_s']:g} s): {g['rsu_lists_sniffed']} RSU lists on the air, "
        f"{g['rsu_lists_accepted']} accepted by the OBU; {g['outputs']} fused outputs, {g['outputs_with_rsu_objects']} "
        f"with RSU objects; output misses {g['output_deadline_misses']} of {g['cycles']} cycles",
        f"  before the attack ({b['window_s']:g} s): {b['rsu_lists_sniffed']} RSU lists on the air, "
        f"{b['rsu_lists_accepted']} accepted; ghost rule false positives {b['false_positive_outputs']} in "
        f"{b['outputs']} outputs; security rejections {_reasons(b['rejected'])}",
    ]
    notes = got_through(report)
    lines.append("  got through: " + ("; ".join(notes) if notes else "nothing"))
    return "\n".join(lines)
