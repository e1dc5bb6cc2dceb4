"""Scrape-time collectors of the services' ``v2i_*`` series (``v2i.telemetry.prometheus`` serves them).

Each collector reads, once per scrape, the node's latest published metrics object (one
attribute read: the node assigns it atomically) and its ``latency`` (``StageLatency``):

- ``ObuCollector``: ``node.last_metrics`` (``ObuMetrics``), labels ``vehicle_id`` and, per RSU,
  ``rsu_id``; the ``rsu_to_obu`` stage is also ``v2i_obu_rsu_delay_seconds``.
- ``RsuCollector``: ``node.last_metrics`` (``RsuMetrics``), label ``rsu_id``.
- ``LinkCollector``: ``node.last_stats`` (the relay's stats dict, ``LinkRelay.stats_snapshot`` /
  ``V2vRelay.stats_snapshot``), labels ``link_id`` and ``direction`` (uplink, downlink; v2v).

Nothing is exported from a metrics message before the first one is published. Units are
Prometheus base units: seconds (the messages carry ns and ms), ratios (drift ppm * 1e-6).
Counters end in ``_total`` (``CounterMetricFamily`` adds it).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, SummaryMetricFamily
from prometheus_client.registry import Collector

from v2i.telemetry.prometheus import MAX_LABEL_VALUES, OTHER, LabelCap, stage_histogram, stage_histograms

RSU_TO_OBU = "rsu_to_obu"
DIRECTIONS = ("uplink", "downlink", "v2v")
NS_TO_S, MS_TO_S, PPM = 1e-9, 1e-3, 1e-6
MAX_RSUS = 64  # ObuMetrics.rsus max_length


def _scaled(value: float | None, factor: float) -> float | None:
    return None if value is None else value * factor


def _counter(name: str, doc: str, labels: dict[str, str], value: float) -> CounterMetricFamily:
    family = CounterMetricFamily(name, doc, labels=list(labels))
    family.add_metric(list(labels.values()), value)
    return family


def _gauge(name: str, doc: str, labels: dict[str, str], value: float) -> GaugeMetricFamily:
    family = GaugeMetricFamily(name, doc, labels=list(labels))
    family.add_metric(list(labels.values()), value)
    return family


def _by_label(kind: type, name: str, doc: str, labels: dict[str, str], label: str,
              counts: Mapping[Any, float], cap: LabelCap) -> Any:
    """One family of ``kind`` with a sample per key of ``counts`` under ``label`` (capped)."""
    family = kind(name, doc, labels=[*labels, label])
    for value, count in cap.counts(counts).items():
        family.add_metric([*labels.values(), value], count)
    return family


class _Caps:
    """One ``LabelCap`` per family name, made on first use (scrape threads share them)."""

    def __init__(self) -> None:
        self._caps: dict[str, LabelCap] = {}

    def __call__(self, family: str) -> LabelCap:
        # rsu_id: as many as an ObuMetrics message may list (64), so every RSU it reports has its series
        return self._caps.setdefault(family, LabelCap(MAX_RSUS if family == "rsu_id" else MAX_LABEL_VALUES))


class ObuCollector(Collector):
    """``v2i_obu_*`` of one OBU node (``last_metrics``: ``ObuMetrics``; ``latency``)."""

    def __init__(self, node: Any) -> None:
        self.node, self._cap = node, _Caps()

    def collect(self) -> Iterator[Any]:
        metrics = getattr(self.node, "last_metrics", None)
        latency = getattr(self.node, "latency", None)
        vid = getattr(metrics, "vehicle_id", None) or getattr(getattr(self.node, "config", None), "vehicle_id", "")
        ids = {"vehicle_id": self._cap("vehicle_id").label(vid)}
        if metrics is not None:
            yield from self._counts(metrics, ids)
            yield from self._rsus(metrics, ids)
        yield stage_histograms("v2i_obu_stage_seconds", "OBU pipeline stage durations (v2i.telemetry.latency)",
                               ids, latency, self._cap("v2i_obu_stage_seconds"))
        yield stage_histogram("v2i_obu_rsu_delay_seconds", "one-way delay, RSU publish stamp -> OBU receive "
                              "(OBU time, through the clock estimate; all RSUs)", ids, latency, RSU_TO_OBU)
        if latency is not None:
            yield _by_label(CounterMetricFamily, "v2i_obu_stage_invalid_total", "stage durations refused "
                            "(NaN, negative: a clock stepped)", ids, "stage", latency.invalid(), self._cap("invalid"))

    def _counts(self, m: Any, ids: dict[str, str]) -> Iterator[Any]:
        yield _counter("v2i_obu_cycles_total", "fusion cycles run", ids, m.cycles)
        yield _counter("v2i_obu_output_deadline_misses_total", "outputs published after capture + deadline, or "
                       "after the output interval bound", ids, m.output_deadline_misses)
        yield _counter("v2i_obu_rsu_deadline_misses_total", "covered cycles fused without RSU data", ids,
                       m.rsu_deadline_misses)
        yield _counter("v2i_obu_covered_cycles_total", "cycles with an RSU heard recently", ids, m.covered_cycles)
        yield _counter("v2i_obu_crowded_out_cycles_total", "cycles that fell back from their best mode while the "
                       "intake refused a registered RSU's (or own sensor's) message", ids, m.crowded_out_cycles)
        yield _by_label(CounterMetricFamily, "v2i_obu_mode_cycles_total", "cycles by fusion mode", ids, "mode",
                        m.mode_counts, self._cap("mode"))
        yield _by_label(GaugeMetricFamily, "v2i_obu_fusion_mode", "the latest cycle's fusion mode (1)", ids,
                        "mode", {m.mode: 1} if m.mode else {}, self._cap("mode"))
        yield _by_label(CounterMetricFamily, "v2i_obu_rejected_total", "inputs rejected, by reason", ids, "reason",
                        m.rejected, self._cap("v2i_obu_rejected_total"))
        yield _by_label(CounterMetricFamily, "v2i_obu_output_dropped_total", "output objects dropped or clipped to "
                        "fit the wire, by reason", ids, "reason", m.output_dropped, self._cap("output_dropped"))
        yield _gauge("v2i_obu_metrics_time_seconds", "OBU clock time of the latest metrics (Unix s)", ids,
                     m.t_ns * NS_TO_S)

    def _rsus(self, m: Any, ids: dict[str, str]) -> Iterator[Any]:
        """Per-RSU families; a field the OBU does not know yet (None) has no sample."""
        cap = self._cap("rsu_id")
        fields = (  # (family, kind, doc, RsuLinkStatus field, factor to base units)
            ("v2i_obu_clock_offset_seconds", GaugeMetricFamily, "estimated RSU clock - OBU clock",
             "clock_offset_ns", NS_TO_S),
            ("v2i_obu_clock_offset_uncertainty_seconds", GaugeMetricFamily, "bound on the offset estimate's error",
             "clock_uncertainty_ns", NS_TO_S),
            ("v2i_obu_clock_offset_naive_seconds", GaugeMetricFamily, "offset from the latest single exchange",
             "clock_offset_naive_ns", NS_TO_S),
            ("v2i_obu_clock_drift_ratio", GaugeMetricFamily, "estimated drift d(offset)/dt (ppm * 1e-6)",
             "clock_drift_ppm", PPM),
            ("v2i_obu_clock_sync_samples_total", CounterMetricFamily, "time exchanges accepted", "sync_samples", 1),
            ("v2i_obu_clock_sync_outliers_total", CounterMetricFamily, "time replies the clock filter rejected",
             "sync_outliers", 1),
            ("v2i_obu_rsu_lists_accepted_total", CounterMetricFamily, "RSU object lists accepted",
             "messages_accepted", 1),
            ("v2i_obu_rsu_lists_sent_total", CounterMetricFamily, "RSU object lists numbered since first heard "
             "(sequence span)", "messages_sent", 1),
            ("v2i_obu_rsu_data_age_seconds", GaugeMetricFamily, "age of the newest RSU data at the latest cycle",
             "last_data_age_ms", MS_TO_S),
            ("v2i_obu_rsu_delay_p50_seconds", GaugeMetricFamily, "one-way delay median (link monitor window)",
             "delay_p50_ms", MS_TO_S),
            ("v2i_obu_rsu_delay_p95_seconds", GaugeMetricFamily, "one-way delay p95 (link monitor window)",
             "delay_p95_ms", MS_TO_S),
            ("v2i_obu_rsu_jitter_seconds", GaugeMetricFamily, "one-way delay jitter", "jitter_ms", MS_TO_S),
            ("v2i_obu_rsu_loss_ratio", GaugeMetricFamily, "RSU lists lost (sequence gaps)", "loss_ratio", 1),
        )
        for name, kind, doc, field, factor in fields:
            family = kind(name, doc, labels=[*ids, "rsu_id"])
            for status in m.rsus:
                value = _scaled(getattr(status, field), factor)
                rsu = cap.label(status.rsu_id)
                if value is not None and rsu != OTHER:  # per-RSU gauges do not add up: past the cap, none
                    family.add_metric([*ids.values(), rsu], value)
            yield family


class RsuCollector(Collector):
    """``v2i_rsu_*`` of one RSU node (``last_metrics``: ``RsuMetrics``; ``latency``)."""

    def __init__(self, node: Any) -> None:
        self.node, self._cap = node, _Caps()

    def collect(self) -> Iterator[Any]:
        m = getattr(self.node, "last_metrics", None)
        rid = getattr(m, "rsu_id", None) or getattr(getattr(self.node, "config", None), "rsu_id", "")
        ids = {"rsu_id": self._cap("rsu_id").label(rid)}
        if m is not None:
            yield _counter("v2i_rsu_published_total", "object lists published", ids, m.published)
            yield _counter("v2i_rsu_skipped_total", "frames not published because their time had passed", ids,
                           m.skipped)
            yield _counter("v2i_rsu_time_replies_total", "time queries answered", ids, m.time_replies)
            yield _by_label(CounterMetricFamily, "v2i_rsu_rejected_total", "inputs rejected, by reason", ids,
                            "reason", m.rejected, self._cap("rejected"))
            yield _gauge("v2i_rsu_metrics_time_seconds", "RSU clock time of the latest metrics (Unix s)", ids,
                         m.t_ns * NS_TO_S)
            if m.perception is not None:
                yield from self._perception(m.perception, ids)
        latency = getattr(self.node, "latency", None)
        yield stage_histograms("v2i_rsu_stage_seconds", "RSU pipeline stage durations (v2i.telemetry.latency)", ids,
                               latency, self._cap("stage"))

    @staticmethod
    def _perception(p: Any, ids: dict[str, str]) -> Iterator[Any]:
        yield _counter("v2i_rsu_perception_frames_total", "frames scored against the simulated truth", ids, p.frames)
        for name, value in (("recall", p.recall), ("precision", p.precision)):
            if value is not None:
                yield _gauge(f"v2i_rsu_perception_{name}_ratio", f"detection {name} against the simulated truth",
                             ids, value)


class LinkCollector(Collector):
    """``v2i_link_*`` of one link emulator (``last_stats``: its stats dict; ``latency``)."""

    def __init__(self, node: Any) -> None:
        self.node, self._cap = node, _Caps()

    def collect(self) -> Iterator[Any]:
        stats = getattr(self.node, "last_stats", None)
        lid = (stats or {}).get("link_id") or getattr(getattr(self.node, "config", None), "link_id", "")
        ids = {"link_id": self._cap("link_id").label(lid)}
        if stats is not None:
            yield from self._directions(stats, ids)
            yield from self._events(stats, ids)
        yield stage_histograms("v2i_link_stage_seconds", "relay stage durations: relay_hold (receive -> scheduled "
                               "send), relay_late (scheduled -> actual send)", ids,
                               getattr(self.node, "latency", None), self._cap("stage"))

    def _directions(self, stats: dict, ids: dict[str, str]) -> Iterator[Any]:
        present = [d for d in DIRECTIONS if isinstance(stats.get(d), dict)]
        labels = [*ids, "direction"]
        counts = {name: CounterMetricFamily(f"v2i_link_{name}_total", doc, labels=labels) for name, doc in (
            ("received", "messages received by the relay"), ("delivered", "messages sent on after their delay"),
            ("dropped", "messages lost (channel loss, outage, caps)"))}
        delay = SummaryMetricFamily("v2i_link_delay_seconds", "delay imposed on delivered messages (sum / count)",
                                    labels=labels)
        delay_max = GaugeMetricFamily("v2i_link_delay_max_seconds", "largest delay imposed so far", labels=labels)
        for d in present:
            row, values = stats[d], [*ids.values(), d]
            for name, family in counts.items():
                family.add_metric(values, row.get(name, 0))
            ms = row.get("delay_ms") or {}
            count, mean = ms.get("count") or 0, ms.get("mean")
            delay.add_metric(values, count, (mean or 0.0) * count * MS_TO_S)
            if ms.get("max") is not None:
                delay_max.add_metric(values, ms["max"] * MS_TO_S)
        yield from (*counts.values(), delay, delay_max)
        in_flight = stats.get("in_flight") or {}
        for unit, doc in (("messages", "messages scheduled and not yet sent"), ("bytes", "their bytes")):
            family = GaugeMetricFamily(f"v2i_link_in_flight_{unit}", doc, labels=labels)
            for d in DIRECTIONS:
                if isinstance(in_flight.get(d), dict):
                    family.add_metric([*ids.values(), d], in_flight[d].get(unit, 0))
            yield family

    def _events(self, stats: dict, ids: dict[str, str]) -> Iterator[Any]:
        late = stats.get("lateness_ms") or {}
        lateness = SummaryMetricFamily("v2i_link_lateness_seconds", "actual - scheduled send time (sum / count)",
                                       labels=list(ids))
        lateness.add_metric(list(ids.values()), late.get("count") or 0,
                            (late.get("mean") or 0.0) * (late.get("count") or 0) * MS_TO_S)
        yield lateness
        yield _by_label(CounterMetricFamily, "v2i_link_refused_total", "arrivals refused by the intake gate, by "
                        "reason", ids, "reason", stats.get("refused") or {}, self._cap("refused"))
        control = stats.get("control") or {}
        yield _counter("v2i_link_control_applied_total", "link controls applied", ids, control.get("applied", 0))
        yield _by_label(CounterMetricFamily, "v2i_link_control_rejected_total", "link controls rejected, by reason",
                        ids, "reason", control.get("rejected") or {}, self._cap("control"))
        if stats.get("profile"):
            yield _by_label(GaugeMetricFamily, "v2i_link_profile_info", "the link profile in force (1)", ids,
                            "profile", {stats["profile"]: 1}, self._cap("profile"))
        if "open_queries" in stats:
            yield _gauge("v2i_link_open_queries", "time queries forwarded and not yet answered", ids,
                         stats["open_queries"])
        yield from self._poses(stats.get("pose") or {}, ids)
        if stats.get("time_ns") is not None:
            yield _gauge("v2i_link_stats_time_seconds", "time of the latest stats (Unix s)", ids,
                         stats["time_ns"] * NS_TO_S)

    def _poses(self, pose: dict, ids: dict[str, str]) -> Iterator[Any]:
        """Ego poses heard: the one-vehicle dict (RSU link) or one per vehicle id (V2V), by ``vehicle_id``."""
        rows = [pose] if "received" in pose else [p for p in pose.values() if isinstance(p, dict)]
        labels, cap = [*ids, "vehicle_id"], self._cap("vehicle_id")
        received = CounterMetricFamily("v2i_link_pose_received_total", "ego poses received", labels=labels)
        rejected = CounterMetricFamily("v2i_link_pose_rejected_total", "ego poses undecodable", labels=labels)
        refused = CounterMetricFamily("v2i_link_pose_refused_total", "ego poses refused, by reason",
                                      labels=[*labels, "reason"])
        distance = GaugeMetricFamily("v2i_link_rsu_distance_meters", "vehicle - RSU distance", labels=labels)
        for row in rows:
            vid = cap.label(row.get("vehicle_id"))
            received.add_metric([*ids.values(), vid], row.get("received", 0))
            rejected.add_metric([*ids.values(), vid], row.get("rejected", 0))
            for reason, n in self._cap("pose_refused").counts(row.get("refused") or {}).items():
                refused.add_metric([*ids.values(), vid, reason], n)
            if row.get("distance_m") is not None:
                distance.add_metric([*ids.values(), vid], row["distance_m"])
        yield from (received, rejected, refused, distance)


def collector_for(service: str, node: Any) -> Collector:
    """The collector of ``service`` (rsu, obu, link) reading ``node``."""
    kinds = {"obu": ObuCollector, "rsu": RsuCollector, "link": LinkCollector}
    if service not in kinds:
        raise ValueError(f"no metrics collector for service {service!r} (one of {', '.join(kinds)})")
    return kinds[service](node)
