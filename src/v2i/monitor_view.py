"""``v2i monitor``'s dashboard: a ``v2i.telemetry.snapshot`` dict drawn as ``rich`` tables (no I/O).

One table per vehicle (misses over the run and the window, mode and shares, per RSU the one-way
delay p50/p95, loss, data age, clock offset +- uncertainty), one for the RSUs, one for the link
emulators (received, delivered, dropped, impairments in force), and the refusals by reason.
"""

from __future__ import annotations

from typing import Any

from rich.console import Group
from rich.table import Table
from rich.text import Text

MAX_VEHICLE_TABLES = 8  # more vehicles: the totals line counts them, the JSON has them all
MAX_REASONS = 12


def pct(value: float | None) -> str:
    return "-" if value is None else f"{value:.1%}"


def num(value: float | None, fmt: str = ".1f", unit: str = "") -> str:
    return "-" if value is None else f"{value:{fmt}}{unit}"


def shares_text(shares: dict[str, float]) -> str:
    return " ".join(f"{mode} {share:.0%}" for mode, share in shares.items()) or "-"


def misses_text(ratios: dict[str, float | None]) -> str:
    return f"{pct(ratios['run'])} / {pct(ratios['window'])}"


def crowded_text(cycles: int) -> str:
    """The cycles that fell back while genuine input was crowded out, when there are any."""
    return f", [bold red]crowded out {cycles}[/bold red]" if cycles else ""


def lists_text(accepted: int, sent: int | None) -> str:
    """Lists accepted, of those the RSU numbered (when known)."""
    return str(accepted) if sent is None else f"{accepted}/{sent}"


def vehicle_table(vid: str, v: dict[str, Any], window_s: float) -> Table:
    """One vehicle: its deadline misses and modes in the title, one row per RSU it hears."""
    title = (f"vehicle {vid}: {v['cycles']} cycles, output misses {misses_text(v['output_miss_ratio'])}, "
             f"RSU misses {misses_text(v['rsu_miss_ratio'])} (run / {window_s:g} s)"
             f"{crowded_text(v['crowded_out_cycles'])}; mode [bold]{v['mode'] or '-'}"
             f"[/bold]; run {shares_text(v['mode_share'])}; {window_s:g} s {shares_text(v['mode_share_window'])}")
    table = Table(title=title, title_justify="left", expand=False)
    for column in ("RSU", "lists (of sent)", "delay p50", "delay p95", "jitter", "loss", "data age", "clock offset", "drift"):
        table.add_column(column, justify="left" if column == "RSU" else "right")
    for rid, r in v["rsus"].items():
        offset = ("-" if r["clock_offset_ms"] is None else
                  f"{r['clock_offset_ms']:+.3f} ± {num(r['clock_uncertainty_ms'], '.3f')} ms")
        table.add_row(rid, lists_text(r["messages_accepted"], r["messages_sent"]), num(r["delay_p50_ms"], ".1f", " ms"),
                      num(r["delay_p95_ms"], ".1f", " ms"), num(r["jitter_ms"], ".1f", " ms"), pct(r["loss_ratio"]),
                      num(r["data_age_ms"], ".0f", " ms"), offset, num(r["clock_drift_ppm"], ".1f", " ppm"))
    if not v["rsus"]:
        table.add_row("(no RSU heard yet)", *["-"] * 8)
    return table


def rsu_table(rsus: dict[str, Any]) -> Table:
    table = Table(title="RSUs", title_justify="left")
    for column in ("RSU", "lists published", "skipped (late)", "time replies", "recall", "age"):
        table.add_column(column, justify="left" if column == "RSU" else "right")
    for rid, r in rsus.items():
        p = r["perception"] or {}
        table.add_row(rid, str(r["published"]), f"{r['skipped']} ({pct(r['skipped_ratio'])})", str(r["time_replies"]),
                      num(p.get("recall"), ".3f"), f"{r['age_s']:.1f} s")
    return table


def link_table(links: dict[str, Any], window_s: float) -> Table:
    table = Table(title="link emulators", title_justify="left")
    for column in ("link", "profile", "direction", "received", "delivered", "dropped", f"drop {window_s:g} s",
                   "delay mean / max", "impairments in force"):
        table.add_column(column, justify="left" if column in ("link", "profile", "direction", "impairments in force")
                         else "right")
    for lid, link in links.items():
        impairments = ", ".join(f"{i['effect']} ({i['left_s']:g} s left)" for i in link["impairments"]) or "none"
        for k, (name, d) in enumerate(link["directions"].items()):
            table.add_row(lid if k == 0 else "", (link["profile"] or "-") if k == 0 else "", name,
                          num(d["received"], "d"), num(d["delivered"], "d"),
                          f"{num(d['dropped'], 'd')} ({pct(d['drop_ratio'])})", pct(link["drop_ratio_window"].get(name)),
                          f"{num(d['delay_mean_ms'])} / {num(d['delay_max_ms'])} ms", impairments if k == 0 else "")
    return table


def rejected_table(snapshot: dict[str, Any]) -> Table | None:
    """Refused inputs by reason, per service; None when nothing was refused."""
    rows = [(f"vehicle {vid}", reason, n) for vid, v in snapshot["vehicles"].items()
            for reason, n in {**v["rejected"], **{f"output_{k}": n for k, n in v["output_dropped"].items()}}.items()]
    rows += [(f"RSU {rid}", reason, n) for rid, r in snapshot["rsus"].items() for reason, n in r["rejected"].items()]
    rows += [(f"link {lid}", reason, n) for lid, link in snapshot["links"].items()
             for reason, n in {**link["refused"], **{f"control_{k}": n for k, n in link["controls_rejected"].items()}}.items()]
    if not rows:
        return None
    table = Table(title="rejected by reason", title_justify="left")
    for column in ("where", "reason", "count"):
        table.add_column(column, justify="right" if column == "count" else "left")
    for where, reason, n in sorted(rows, key=lambda row: -row[2])[:MAX_REASONS]:
        table.add_row(where, reason, str(n))
    return table


def latency_table(snapshot: dict[str, Any]) -> Table | None:
    """Per-stage latency (ms) of each service that sends ``latency_ms``; None when none does."""
    sources = [(f"vehicle {vid}", v["latency_ms"]) for vid, v in snapshot["vehicles"].items()]
    sources += [(f"RSU {rid}", r["latency_ms"]) for rid, r in snapshot["rsus"].items()]
    sources += [(f"link {lid}", link.get("latency_ms")) for lid, link in snapshot["links"].items()]
    rows = [(where, stage, q) for where, stages in sources if stages for stage, q in stages.items()]
    if not rows:
        return None
    table = Table(title="latency by stage (ms)", title_justify="left")
    for column in ("where", "stage", "count", "p50", "p95", "p99"):
        table.add_column(column, justify="left" if column in ("where", "stage") else "right")
    for k, (where, stage, q) in enumerate(rows):
        table.add_row(where if k == 0 or rows[k - 1][0] != where else "", stage, num(q.get("count"), "d"),
                      num(q.get("p50"), ".2f"), num(q.get("p95"), ".2f"), num(q.get("p99"), ".2f"))
    return table


def status_line(snapshot: dict[str, Any], sources: list[dict[str, Any]]) -> Text:
    t = snapshot["totals"]
    intake = snapshot["intake"]
    connected = ", ".join(f"{s['endpoint']} ({'up' if s['connected'] else 'down'}, {s['messages']} msgs)" for s in sources)
    bad = sum(intake["undecodable"].values()) + sum(intake["ignored"].values())
    return Text(f"v2i monitor: {connected}; {t['vehicles']} vehicles, {len(snapshot['rsus'])} RSUs, "
                f"{len(snapshot['links'])} links; undecodable or ignored {bad}")


def dashboard(snapshot: dict[str, Any], sources: list[dict[str, Any]]) -> Group:
    """The whole screen for one snapshot; ``sources``: ``{"endpoint", "connected", "messages"}`` each."""
    window_s = snapshot["window_s"]
    parts: list[Any] = [status_line(snapshot, sources)]
    vehicles = list(snapshot["vehicles"].items())
    parts += [vehicle_table(vid, v, window_s) for vid, v in vehicles[:MAX_VEHICLE_TABLES]]
    if len(vehicles) > MAX_VEHICLE_TABLES:
        parts.append(Text(f"... and {len(vehicles) - MAX_VEHICLE_TABLES} more vehicles (--once --json - lists all)"))
    if snapshot["rsus"]:
        parts.append(rsu_table(snapshot["rsus"]))
    if snapshot["links"]:
        parts.append(link_table(snapshot["links"], window_s))
    for table in (latency_table(snapshot), rejected_table(snapshot)):
        if table is not None:
            parts.append(table)
    if not vehicles and not snapshot["rsus"] and not snapshot["links"]:
        parts.append(Text("waiting for v2x/**/metrics and v2x/link/*/stats ..."))
    return Group(*parts)
