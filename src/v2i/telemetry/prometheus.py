"""Prometheus ``/metrics`` of a service process (``--metrics-port``), thin I/O over ``prometheus_client``.

Each service builds one ``CollectorRegistry`` holding a collector of its own
(``v2i.telemetry.prometheus_collectors``) and the process collector (CPU seconds, resident
memory, open file descriptors). The collectors hold no counters: at scrape time they read
what the node last published (``node.last_metrics``, the relay's ``node.last_stats``) and its
``node.latency`` (``v2i.telemetry.latency.StageLatency``), so a scrape shows exactly the numbers of
the metrics messages that ``v2i demo`` scores, never a second count that could drift from them.

Label values come from validated ids and bounded reason strings; ``LabelCap`` also bounds how
many distinct values a family may take (later ones are summed under ``OTHER``), so a flood of
new reasons cannot grow the exporter's memory or the Prometheus server's series.

Listens on 127.0.0.1 unless told otherwise (``--metrics-address 0.0.0.0`` in containers); the
HTTP server runs on a daemon thread and is closed when the node stops.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from typing import Any

from prometheus_client import CollectorRegistry, ProcessCollector, start_http_server
from prometheus_client.core import HistogramMetricFamily
from prometheus_client.utils import floatToGoString

from v2i.telemetry.latency import BUCKETS_S
from v2i.telemetry.metrics_port import DEFAULT_ADDRESS, MetricsPortError

MAX_LABEL_VALUES = 32  # distinct values per label of a family; later ones are summed under OTHER
MAX_LABEL_CHARS = 64
OTHER = "_other"  # the label value of everything past the cap (underscore: no real id or reason has one)


class LabelCap:
    """Admits the first ``max_values`` distinct label values it sees; later ones map to ``OTHER``.

    Stable over scrapes: an admitted value stays admitted, so each series' counter only grows
    (``OTHER`` is the sum of every value refused, itself growing). Thread-safe: concurrent
    scrapes share it.
    """

    def __init__(self, max_values: int = MAX_LABEL_VALUES) -> None:
        if max_values < 1:
            raise ValueError(f"max_values must be >= 1, got {max_values}")
        self.max_values = max_values
        self._admitted: set[str] = set()
        self._lock = threading.Lock()

    def label(self, value: Any) -> str:
        """The label value for ``value`` (None: ""; text cut at ``MAX_LABEL_CHARS``), or ``OTHER``."""
        text = "" if value is None else str(value)[:MAX_LABEL_CHARS]
        with self._lock:
            if text in self._admitted:
                return text
            if len(self._admitted) < self.max_values:
                self._admitted.add(text)
                return text
        return OTHER

    def counts(self, counts: Mapping[Any, float]) -> dict[str, float]:
        """``counts`` keyed by label value, values past the cap summed under ``OTHER``."""
        out: dict[str, float] = {}
        for key in sorted(counts, key=str):  # sorted: which values are admitted first does not depend on dict order
            label = self.label(key)
            out[label] = out.get(label, 0) + counts[key]
        return out


def bucket_pairs(cumulative: list[int]) -> list[tuple[str, float]]:
    """``[(le, count), ...]`` for ``HistogramMetricFamily`` from cumulative counts per ``BUCKETS_S``
    bound with +Inf last (``StageLatency.histogram``)."""
    if len(cumulative) != len(BUCKETS_S) + 1:
        raise ValueError(f"expected {len(BUCKETS_S) + 1} cumulative counts, got {len(cumulative)}")
    bounds = [floatToGoString(b) for b in BUCKETS_S] + ["+Inf"]
    return list(zip(bounds, (float(c) for c in cumulative)))


def stage_histograms(name: str, doc: str, base_labels: dict[str, str], latency: Any,
                     cap: LabelCap) -> HistogramMetricFamily:
    """One histogram family ``name`` with a ``stage`` label: each stage of ``latency`` (None: no sample).

    Stages past ``cap`` add up under ``OTHER`` (bucket by bucket: still a histogram).
    """
    family = HistogramMetricFamily(name, doc, labels=[*base_labels, "stage"])
    merged: dict[str, tuple[list[int], float]] = {}
    for stage in latency.stages() if latency is not None else []:
        cumulative, sum_s, _ = latency.histogram(stage)
        label = cap.label(stage)
        if label in merged:
            old, old_sum_s = merged[label]
            cumulative, sum_s = [a + b for a, b in zip(old, cumulative)], old_sum_s + sum_s
        merged[label] = (cumulative, sum_s)
    for label, (cumulative, sum_s) in merged.items():
        family.add_metric([*base_labels.values(), label], bucket_pairs(cumulative), sum_s)
    return family


def stage_histogram(name: str, doc: str, labels: dict[str, str], latency: Any, stage: str) -> HistogramMetricFamily:
    """One stage of ``latency`` as its own histogram family (no sample before the stage is first observed)."""
    family = HistogramMetricFamily(name, doc, labels=list(labels))
    if latency is not None and stage in latency.stages():
        cumulative, sum_s, _ = latency.histogram(stage)
        family.add_metric(list(labels.values()), bucket_pairs(cumulative), sum_s)
    return family


class MetricsServer:
    """``/metrics`` of one registry over HTTP on a daemon thread; ``close()`` stops it."""

    def __init__(self, registry: CollectorRegistry, port: int, address: str = DEFAULT_ADDRESS) -> None:
        try:
            self._httpd, self._thread = start_http_server(port, address, registry)
        except OSError as exc:
            reason = exc.strerror or str(exc)
            raise MetricsPortError(f"--metrics-port {port}: cannot listen on {address}:{port}: {reason}") from None
        self.address, self.port = address, self._httpd.server_port

    @property
    def url(self) -> str:
        host = f"[{self.address}]" if ":" in self.address else self.address
        return f"http://{host}:{self.port}/metrics"

    def close(self) -> None:
        self._httpd.shutdown()
        self._httpd.server_close()
        self._thread.join(5.0)


def registry_for(collector: Any) -> CollectorRegistry:
    """A registry of its own holding ``collector`` and this process's CPU, memory and descriptors."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    ProcessCollector(registry=registry)
    return registry


def serve(collector: Any, port: int, address: str = DEFAULT_ADDRESS) -> MetricsServer | None:
    """Serve ``collector`` on ``address:port`` (None when ``port`` is 0: off); MetricsPortError if it cannot."""
    if not port:
        return None
    return MetricsServer(registry_for(collector), port, address)
