"""Accounting and table of ``v2i attack`` (pure): what each attack kind did to the OBU and the link.

The OBU's ``ObuMetrics.rejected`` and the emulator's ``control.rejected`` are cumulative counters;
each kind runs in its own phase, so the counters' growth over the phase (plus a settling time)
is what that kind caused. Labels: ``security_<reason>`` = dropped by the verifier,
``security_accepted_<reason>`` = failed but let through (``permissive``), anything else = a
later refusal (e.g. admission's ``duplicate`` for a replay the verifier let through).
"""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Mapping, Sequence

from v2i.adversary.attack_messages import HOSTILE_KINDS, INTENDED

DROP, ACCEPT = "security_", "security_accepted_"
TRACKING_MODES = ("intra", "inter")  # the cycles that fuse RSU data into the tracks
GENUINE_ACCEPTED_MIN = 0.95  # a flood costs the genuine RSU nothing: >= 95 % of its lists accepted
FIRST_SYNC_MAX_S = 3.0  # a time relay from the OBU's start: synchronised within this


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
        if kind in HOSTILE_KINDS:
            notes += hostile_notes(kind, row)
            continue
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
        if kind in HOSTILE_KINDS:
            lines.append(_hostile_line(kind, row))
            continue
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


# --- the opt-in kinds against the genuine RSU's share (issue 32) ---------------------------------------
def genuine_sent_in(sniffed_ns: Sequence[int], t0_ns: int, t1_ns: int, delay_ns: int) -> int:
    """Genuine lists (sniffed at the RSU at ``sniffed_ns``, sorted) that reached the OBU in its
    metrics window (t0, t1]: sniffed in (t0 - delay, t1 - delay], ``delay`` the one-way RSU ->
    OBU delay (the OBU's ``delay_p50_ms``), so that lists in flight at either end count once."""
    return bisect_right(sniffed_ns, t1_ns - delay_ns) - bisect_right(sniffed_ns, t0_ns - delay_ns)


def tracking_share(modes: Mapping[str, int]) -> float | None:
    """The share of cycles in intra- or inter-frame mode (None without cycles)."""
    total = sum(modes.values())
    return sum(modes.get(m, 0) for m in TRACKING_MODES) / total if total else None


def flood_row(sent: Mapping[str, int], rate_hz: float, send_s: float, genuine_sent: int, genuine_accepted: int,
              obu_delta: Mapping[str, int], modes: Mapping[str, int], misses: int, cycles: int, ghost_outputs: int,
              outputs: int, window_s: float, crowded_out: int = 0) -> dict:
    """The ``flood`` kind's line: what it sent (by variant, the rate asked and achieved), what the
    OBU refused, and what the genuine RSU lost in the window (its lists sent and accepted, the cycles
    the OBU counted as crowded out)."""
    dropped, accepted, other = split_labels(obu_delta)
    total = sum(sent.values())
    return {"sent": total, "variants": dict(sent), "rate_hz": rate_hz,
            "achieved_hz": round(total / send_s, 1) if send_s > 0 else 0.0, "send_s": round(send_s, 2),
            "rejected": dropped, "rejected_total": sum(dropped.values()),
            "rejected_as_intended": sum(dropped.get(r, 0) for r in INTENDED["flood"]), "accepted": accepted,
            "other_refusals": other, "genuine_sent": genuine_sent, "genuine_accepted": genuine_accepted,
            "modes": dict(modes), "output_deadline_misses": misses, "cycles": cycles, "crowded_out_cycles": crowded_out,
            "ghost_outputs": ghost_outputs, "outputs": outputs, "window_s": round(window_s, 2)}


def relay_row(relay: Mapping[str, int], before, after, first_sync_s: float | None, reference_offset_ns: int | None,
              clock_samples: Sequence[tuple[int, int, int]], obu_delta: Mapping[str, int], modes: Mapping[str, int],
              misses: int, cycles: int, window_s: float, delay_ms: float = 0.0) -> dict:
    """A time relay kind's line. ``relay``: the relay's counts; ``before`` / ``after``: the RSU's
    ``RsuLinkStatus`` in the OBU's metrics at the window's ends (``before`` None: from the OBU's
    start); ``clock_samples``: (t_ns, offset_ns, uncertainty_ns) of the OBU's estimate in the window;
    ``reference_offset_ns``: the attacker's own estimate of the RSU clock (captured generation time
    minus receive time); the offset error is the OBU's last estimate minus it."""
    last = clock_samples[-1] if clock_samples else None
    error_ms = None if last is None or reference_offset_ns is None else (last[1] - reference_offset_ns) / 1e6
    grown = lambda field: getattr(after, field, 0) - getattr(before, field, 0) if after else 0  # noqa: E731
    return {"relay": dict(relay), "delay_ms": delay_ms, "first_sync_s": first_sync_s,
            "sync_samples": grown("sync_samples"), "clock_steps": grown("clock_steps"),
            "offset_ms": None if last is None else round(last[1] / 1e6, 3),
            "uncertainty_ms": None if last is None else round(last[2] / 1e6, 3),
            "reference_offset_ms": None if reference_offset_ns is None else round(reference_offset_ns / 1e6, 3),
            "offset_error_ms": None if error_ms is None else round(error_ms, 3),
            "clock_samples": [list(s) for s in clock_samples], "rejected": dict(obu_delta), "modes": dict(modes),
            "tracking_share": tracking_share(modes), "output_deadline_misses": misses, "cycles": cycles,
            "window_s": round(window_s, 2)}


def hostile_notes(kind: str, row: dict) -> list[str]:
    """What an opt-in kind cost the genuine RSU (empty: nothing)."""
    notes = []
    if kind == "flood":
        if row["genuine_accepted"] < GENUINE_ACCEPTED_MIN * row["genuine_sent"]:
            notes.append(f"flood: the OBU accepted {row['genuine_accepted']} of the genuine RSU's {row['genuine_sent']} "
                         f"lists (at {row['achieved_hz']:g} msg/s)")
        if row["accepted"]:
            notes.append(f"flood: {sum(row['accepted'].values())} of {row['sent']} failed verification and were accepted")
        if row["ghost_outputs"]:
            notes.append(f"flood: a ghost in {row['ghost_outputs']} fused outputs")
        return notes
    sync = row["first_sync_s"]
    if sync is None:
        notes.append(f"{kind}: the OBU never synchronised its clock to the RSU")
    elif sync > FIRST_SYNC_MAX_S:
        notes.append(f"{kind}: the OBU's clock synchronised only {sync:.1f} s after its start")
    if row["clock_steps"]:
        notes.append(f"{kind}: {row['clock_steps']} RSU clock steps confirmed (none happened)")
    return notes


def _hostile_line(kind: str, row: dict) -> str:
    modes = ", ".join(f"{m} {n}" for m, n in row["modes"].items()) or "-"
    if kind == "flood":
        return (f"  {kind:<10}{row['sent']:>6}{row['rejected_total']:>9}  {_reasons(row['rejected']):<44}"
                f"at {row['achieved_hz']:g}/s (asked {row['rate_hz']:g}); genuine accepted {row['genuine_accepted']} of "
                f"{row['genuine_sent']}; other refusals {_reasons(row['other_refusals'])}; ghost in {row['ghost_outputs']} "
                f"of {row['outputs']} outputs; output misses {row['output_deadline_misses']} of {row['cycles']} cycles; "
                f"modes {modes}; crowded out {row['crowded_out_cycles']}")
    relay = row["relay"]
    sync = "never" if row["first_sync_s"] is None else f"{row['first_sync_s']:.1f} s"
    share = "-" if row["tracking_share"] is None else f"{100 * row['tracking_share']:.0f} %"
    return (f"  {kind:<12} relayed {relay.get('forwarded', 0)} of {relay.get('queries', 0)} queries "
            f"(delay {row['delay_ms']:g} ms), RSU answered {relay.get('rsu_replies', 0)}, returned "
            f"{relay.get('returned', 0)}; synced {sync}; samples +{row['sync_samples']}, steps +{row['clock_steps']}; "
            f"offset {row['offset_ms']} ms +- {row['uncertainty_ms']} (attacker's reference "
            f"{row['reference_offset_ms']} ms); intra/inter {share} of {row['cycles']} cycles; misses "
            f"{row['output_deadline_misses']}; time replies refused {_reasons(row['rejected'])}")
