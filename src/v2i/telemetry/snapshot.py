"""The live state of a v2i site from its metrics messages (pure: receive times are arguments).

``TelemetryBoard`` is fed what ``v2i monitor`` (or a demo) receives, each with its receive time
(ns, the monitor's clock, used for the 10 s windows and ages only):

- ``ObuMetrics`` on ``v2x/obu/{vid}/metrics`` (every cycle): running totals of cycles, output and
  RSU deadline misses, modes, rejected inputs, and per RSU the link and clock view;
- ``RsuMetrics`` on ``v2x/rsu/{id}/metrics``: lists published, frames skipped, refusals;
- the link emulators' stats JSON on ``v2x/link/{id}/stats`` (``v2i.telemetry.link_view``).

It keeps the latest of each and, from successive totals (``v2i.telemetry.windowed``), the ratios over
the last ``window_s``. Memory is bounded whatever arrives: at most ``max_nodes`` vehicles, RSUs
and links each (later ones are counted in ``intake.ignored``), each message's maps bounded by its
schema; payloads that do not decode are counted in ``intake.undecodable``, never raised.

``snapshot(now_ns)`` keys (JSON-ready; ratios in [0, 1] or None before any denominator, ms and s
in the names):

- ``window_s``; ``totals``: ``vehicles``, ``cycles``, ``output_deadline_misses``,
  ``covered_cycles``, ``rsu_deadline_misses``, ``crowded_out_cycles``, ``output_miss_ratio`` / ``rsu_miss_ratio``
  (``{"run", "window"}``: summed over vehicles), ``modes`` (current mode -> vehicles),
  ``rsu_lists_received``, ``vehicles_hearing_no_rsu`` (vehicles whose latest metrics name no RSU);
- ``vehicles.{vid}``: ``messages``, ``age_s`` (since the latest), ``cycles``, ``covered_cycles``,
  ``output_deadline_misses``, ``rsu_deadline_misses``, ``crowded_out_cycles`` (fell back while the intake
  refused a registered RSU's input), ``output_miss_ratio`` and
  ``rsu_miss_ratio`` (``{"run", "window"}``; RSU misses per covered cycle, as the report),
  ``mode``, ``mode_share`` (run), ``mode_share_window``, ``window_span_s``, ``restarts``
  (counters that went down), ``rsu_lists_received``, ``rsu_heard`` (False until its metrics
  name an RSU: before the first list arrives, ``rsus`` is empty), ``rsus.{rsu_id}`` (``delay_p50_ms``,
  ``delay_p95_ms``, ``jitter_ms``, ``loss_ratio``, ``data_age_ms``, ``clock_offset_ms``,
  ``clock_uncertainty_ms``, ``clock_drift_ppm``, ``sync_samples``, ``sync_outliers``,
  ``messages_accepted``, ``messages_sent``: lists the RSU numbered since first heard, or None), ``rejected`` and ``output_dropped`` (reason -> count), ``latency_ms``
  (stage -> p50/p95/p99, when the OBU sends it, else None);
- ``rsus.{rsu_id}``: ``messages``, ``age_s``, ``published``, ``skipped``, ``skipped_ratio``,
  ``time_replies``, ``rejected``, ``perception`` (``frames``, ``recall``, ``precision`` or None),
  ``latency_ms``;
- ``links.{link_id}``: ``messages``, ``age_s``, ``kind`` (rsu / v2v), ``profile``, ``time_ns``,
  ``directions.{downlink|uplink|v2v}`` (``received``, ``delivered``, ``dropped``,
  ``drop_ratio``, ``delay_mean_ms``, ``delay_max_ms``), ``drop_ratio_window``, ``window_span_s``,
  ``lateness_mean_ms``, ``lateness_max_ms``, ``refused``, ``controls_applied``,
  ``controls_rejected``, ``latency_ms`` (stage -> p50/p95/p99, or None), ``pairs``, ``impairments``
  (in force: ``effect``, ``left_s``);
- ``intake``: ``messages`` (obu_metrics / rsu_metrics / link_stats -> count), ``undecodable``
  (kind -> count), ``ignored`` (reason -> count: ``vehicles_over_cap``, ``rsus_over_cap``,
  ``links_over_cap``, ``id_mismatch``, ``other_key``, ``oversized``).
"""

from __future__ import annotations

import json
from collections import Counter
from typing import Any

from schemas.codec import CodecError, decode
from schemas.keys import ID_PATTERN
from schemas.messages import ObuMetrics, RsuLinkStatus, RsuMetrics

from v2i.telemetry.link_view import LinkView
from v2i.telemetry.windowed import WindowedCounters, ratio, shares

WINDOW_S = 10.0
MAX_NODES = 64  # vehicles, RSUs and links tracked, each
MAX_STATS_BYTES = 1 << 20  # a link stats JSON larger than this is refused (20 pairs: ~10 kB)
NS_PER_MS = 1_000_000
_COUNTERS = ("cycles", "output_deadline_misses", "covered_cycles", "rsu_deadline_misses", "crowded_out_cycles")


def _ms(ns: int | None) -> float | None:
    return None if ns is None else round(ns / NS_PER_MS, 3)


def rsu_status_view(r: RsuLinkStatus) -> dict[str, Any]:
    """One RSU as a vehicle sees it: one-way delay, loss, data age, clock offset +- uncertainty."""
    return {"delay_p50_ms": r.delay_p50_ms, "delay_p95_ms": r.delay_p95_ms, "jitter_ms": r.jitter_ms,
            "loss_ratio": r.loss_ratio, "data_age_ms": r.last_data_age_ms,
            "clock_offset_ms": _ms(r.clock_offset_ns), "clock_uncertainty_ms": _ms(r.clock_uncertainty_ns),
            "clock_drift_ppm": r.clock_drift_ppm, "sync_samples": r.sync_samples,
            "sync_outliers": r.sync_outliers, "messages_accepted": r.messages_accepted,
            "messages_sent": r.messages_sent}


class VehicleView:
    """The latest ``ObuMetrics`` of one vehicle and its totals over the window."""

    def __init__(self, window_ns: int):
        self.messages = 0
        self.last_receive_ns = 0
        self.latest: ObuMetrics | None = None
        self._window = WindowedCounters(window_ns)

    def update(self, m: ObuMetrics, receive_ns: int) -> None:
        self.messages += 1
        self.last_receive_ns = receive_ns
        self.latest = m
        modes = {f"mode_{k}": v for k, v in m.mode_counts.items()}
        self._window.add(receive_ns, {**{k: getattr(m, k) for k in _COUNTERS}, **modes})

    def window_delta(self) -> tuple[float, dict[str, int]]:
        return self._window.delta()

    def hears_rsu(self) -> bool:
        """True once its metrics name an RSU (an OBU reports an RSU from the first list it accepts)."""
        return self.latest is not None and bool(self.latest.rsus)

    def snapshot(self, now_ns: int) -> dict[str, Any]:
        m = self.latest
        span_s, d = self._window.delta()
        window_modes = {k[5:]: v for k, v in d.items() if k.startswith("mode_")}
        return {
            "messages": self.messages, "age_s": round((now_ns - self.last_receive_ns) * 1e-9, 2),
            **{k: getattr(m, k) for k in _COUNTERS},
            "output_miss_ratio": {"run": ratio(m.output_deadline_misses, m.cycles),
                                  "window": ratio(d.get("output_deadline_misses", 0), d.get("cycles", 0))},
            "rsu_miss_ratio": {"run": ratio(m.rsu_deadline_misses, m.covered_cycles),
                               "window": ratio(d.get("rsu_deadline_misses", 0), d.get("covered_cycles", 0))},
            "mode": m.mode, "mode_share": shares(m.mode_counts), "mode_share_window": shares(window_modes),
            "window_span_s": round(span_s, 2), "restarts": self._window.resets,
            "rsu_lists_received": sum(r.messages_accepted for r in m.rsus), "rsu_heard": self.hears_rsu(),
            "rsus": {r.rsu_id: rsu_status_view(r) for r in m.rsus},
            "rejected": dict(m.rejected), "output_dropped": dict(m.output_dropped),
            "latency_ms": _latency(m),
        }


def _latency(message) -> Any:
    """The optional ``latency_ms`` field of a metrics message, JSON-ready, or None."""
    value = getattr(message, "latency_ms", None)
    if not value:
        return None
    return {stage: s.model_dump(mode="json") if hasattr(s, "model_dump") else s for stage, s in value.items()}


def rsu_view(m: RsuMetrics, messages: int, receive_ns: int, now_ns: int) -> dict[str, Any]:
    p = m.perception
    return {"messages": messages, "age_s": round((now_ns - receive_ns) * 1e-9, 2), "published": m.published,
            "skipped": m.skipped, "skipped_ratio": ratio(m.skipped, m.published + m.skipped),
            "time_replies": m.time_replies, "rejected": dict(m.rejected),
            "perception": None if p is None else {"frames": p.frames, "recall": p.recall, "precision": p.precision},
            "latency_ms": _latency(m)}


class TelemetryBoard:
    """Everything the monitor shows, fed one message at a time (one thread; not locked)."""

    def __init__(self, window_s: float = WINDOW_S, max_nodes: int = MAX_NODES):
        self.window_s, self.max_nodes = window_s, max_nodes
        self._window_ns = round(window_s * 1e9)
        self.vehicles: dict[str, VehicleView] = {}
        self.rsus: dict[str, tuple[RsuMetrics, int, int]] = {}  # id -> (latest, messages, receive_ns)
        self.links: dict[str, LinkView] = {}
        self.received: Counter[str] = Counter()
        self.undecodable: Counter[str] = Counter()
        self.ignored: Counter[str] = Counter()

    # ---- intake -----------------------------------------------------------------------

    def on_sample(self, key: str, payload: bytes, receive_ns: int) -> str:
        """Route one Zenoh sample by its key; returns its kind (``obu_metrics``, ``rsu_metrics``,
        ``link_stats``) or ``ignored`` / ``undecodable``."""
        parts = key.split("/")
        if len(parts) != 4 or parts[0] != "v2x" or not ID_PATTERN.fullmatch(parts[2]):
            return self._ignore("other_key")
        kind = {("obu", "metrics"): "obu_metrics", ("rsu", "metrics"): "rsu_metrics",
                ("link", "stats"): "link_stats"}.get((parts[1], parts[3]))
        if kind is None:
            return self._ignore("other_key")
        try:
            if kind == "obu_metrics":
                accepted = self.on_obu_metrics(decode(payload, ObuMetrics), receive_ns, parts[2])
            elif kind == "rsu_metrics":
                accepted = self.on_rsu_metrics(decode(payload, RsuMetrics), receive_ns, parts[2])
            else:
                accepted = self.on_link_stats(self._stats_json(payload), receive_ns, parts[2])
        except (CodecError, ValueError, RecursionError):
            self.undecodable[kind] += 1
            return "undecodable"
        return kind if accepted else "ignored"

    def _stats_json(self, payload: bytes) -> dict[str, Any]:
        """The stats dict in ``payload``; ValueError when it is too large, not JSON or not an object."""
        if len(payload) > MAX_STATS_BYTES:
            raise ValueError(f"link stats of {len(payload)} bytes")
        stats = json.loads(payload)  # JSONDecodeError, UnicodeDecodeError: ValueErrors; deep: RecursionError
        if not isinstance(stats, dict):
            raise ValueError("link stats are not a JSON object")  # noqa: TRY004 - a bad payload, counted as such
        return stats

    def _ignore(self, reason: str) -> str:
        self.ignored[reason] += 1
        return "ignored"

    def _admit(self, table: dict, node_id: str, key_id: str | None, what: str) -> bool:
        """True when ``node_id`` matches its key and is tracked or fits under the cap."""
        if key_id is not None and node_id != key_id:
            self.ignored["id_mismatch"] += 1
            return False
        if node_id not in table and len(table) >= self.max_nodes:
            self.ignored[f"{what}_over_cap"] += 1
            return False
        return True

    def on_obu_metrics(self, m: ObuMetrics, receive_ns: int, key_id: str | None = None) -> bool:
        """One vehicle's metrics; False when ignored (id not its key's, or over the cap)."""
        if not self._admit(self.vehicles, m.vehicle_id, key_id, "vehicles"):
            return False
        self.received["obu_metrics"] += 1
        self.vehicles.setdefault(m.vehicle_id, VehicleView(self._window_ns)).update(m, receive_ns)
        return True

    def on_rsu_metrics(self, m: RsuMetrics, receive_ns: int, key_id: str | None = None) -> bool:
        if not self._admit(self.rsus, m.rsu_id, key_id, "rsus"):
            return False
        self.received["rsu_metrics"] += 1
        _, messages, _ = self.rsus.get(m.rsu_id, (None, 0, 0))
        self.rsus[m.rsu_id] = (m, messages + 1, receive_ns)
        return True

    def on_link_stats(self, stats: dict[str, Any], receive_ns: int, key_id: str | None = None) -> bool:
        """One link emulator's stats dict; ValueError when it names no valid link id."""
        link_id = stats.get("link_id")
        if not isinstance(link_id, str) or not ID_PATTERN.fullmatch(link_id):
            raise ValueError("link stats without a valid link_id")
        if not self._admit(self.links, link_id, key_id, "links"):
            return False
        self.received["link_stats"] += 1
        self.links.setdefault(link_id, LinkView(link_id, self._window_ns)).update(stats, receive_ns)
        return True

    # ---- output -----------------------------------------------------------------------

    def snapshot(self, now_ns: int) -> dict[str, Any]:
        """Everything as of ``now_ns`` (the receive clock); the keys are in the module docstring."""
        return {
            "window_s": self.window_s,
            "totals": self.totals(),
            "vehicles": {vid: v.snapshot(now_ns) for vid, v in sorted(self.vehicles.items())},
            "rsus": {rid: rsu_view(m, n, t, now_ns) for rid, (m, n, t) in sorted(self.rsus.items())},
            "links": {lid: link.snapshot(now_ns) for lid, link in sorted(self.links.items())},
            "intake": {"messages": dict(self.received), "undecodable": dict(self.undecodable),
                       "ignored": dict(self.ignored)},
        }

    def totals(self) -> dict[str, Any]:
        """Counters summed over the vehicles (run and window), current modes, RSU lists received."""
        run, window = Counter(), Counter()
        modes: Counter[str] = Counter()
        lists = 0
        for v in self.vehicles.values():
            run.update({k: getattr(v.latest, k) for k in _COUNTERS})
            window.update({k: n for k, n in v.window_delta()[1].items() if k in _COUNTERS})
            modes[v.latest.mode or "none"] += 1
            lists += sum(r.messages_accepted for r in v.latest.rsus)
        return {
            "vehicles": len(self.vehicles), **{k: run[k] for k in _COUNTERS},
            "output_miss_ratio": {"run": ratio(run["output_deadline_misses"], run["cycles"]),
                                  "window": ratio(window["output_deadline_misses"], window["cycles"])},
            "rsu_miss_ratio": {"run": ratio(run["rsu_deadline_misses"], run["covered_cycles"]),
                               "window": ratio(window["rsu_deadline_misses"], window["covered_cycles"])},
            "modes": dict(modes), "rsu_lists_received": lists,
            "vehicles_hearing_no_rsu": sum(not v.hears_rsu() for v in self.vehicles.values()),
        }

