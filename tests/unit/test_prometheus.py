"""``/metrics`` collectors (``v2i.telemetry.prometheus_collectors``) against nodes without Zenoh: names,
labels and values equal to the metrics message they read, histograms cumulative, label values
capped, and the HTTP exporter's start-up errors."""

from __future__ import annotations

import json
import re
import socket
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml
from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families

from v2i.orchestration.demo import METRICS_PORT_OFFSETS
from link_emulator.config import LinkConfig
from link_emulator.relay import LinkRelay
from link_emulator.v2v_relay import V2vRelay
from schemas.messages import ObuMetrics, RsuLinkStatus, RsuMetrics, RsuPerception
from v2i.sim.clock import SystemClock
from v2i.telemetry.latency import BUCKETS_S, StageLatency
from v2i.telemetry.metrics_cli import MetricsPortError
from v2i.telemetry.prometheus import OTHER, LabelCap, MetricsServer, bucket_pairs, registry_for, serve
from v2i.telemetry.prometheus_collectors import LinkCollector, ObuCollector, RsuCollector, collector_for

T0 = 1_767_225_600_000_000_000
EP = ["tcp/127.0.0.1:1"]
DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def scrape(collector) -> dict[str, dict[tuple, float]]:
    """Every sample of a scrape, parsed back from the text format: {sample name: {sorted labels: value}}."""
    text = generate_latest(registry_for(collector)).decode()
    out: dict[str, dict[tuple, float]] = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out.setdefault(s.name, {})[tuple(sorted(s.labels.items()))] = s.value
    return out


def one(samples: dict, name: str, **labels) -> float:
    return samples[name][tuple(sorted(labels.items()))]


def obu_metrics(**fields) -> ObuMetrics:
    rsu1 = RsuLinkStatus(rsu_id="rsu1", clock_offset_ns=250_000_000, clock_uncertainty_ns=400_000,
                         clock_drift_ppm=12.0, clock_offset_naive_ns=251_000_000, sync_samples=40, sync_outliers=2,
                         messages_accepted=95, last_data_age_ms=120.0, delay_p50_ms=4.7, delay_p95_ms=7.9,
                         jitter_ms=1.5, loss_ratio=0.02)
    rsu2 = RsuLinkStatus(rsu_id="rsu2", messages_accepted=3)  # heard, no clock estimate yet
    base = dict(vehicle_id="car1", t_ns=T0, cycles=200, output_deadline_misses=3, rsu_deadline_misses=7,
                covered_cycles=180, mode="intra", mode_counts={"intra": 150, "inter": 30, "vehicle-only": 20},
                rsus=(rsu1, rsu2), rejected={"stale": 4, "codec": 1}, output_dropped={"too_many": 2})
    return ObuMetrics(**(base | fields))


def latency_with(observations: dict[str, list[float]]) -> StageLatency:
    latency = StageLatency()
    for stage, values in observations.items():
        for v in values:
            latency.observe(stage, v)
    return latency


def test_obu_counters_and_gauges_are_the_metrics_message_in_base_units():
    m = obu_metrics()
    s = scrape(ObuCollector(SimpleNamespace(last_metrics=m, latency=StageLatency())))
    car = {"vehicle_id": "car1"}
    assert one(s, "v2i_obu_cycles_total", **car) == 200
    assert one(s, "v2i_obu_output_deadline_misses_total", **car) == 3
    assert one(s, "v2i_obu_rsu_deadline_misses_total", **car) == 7
    assert one(s, "v2i_obu_covered_cycles_total", **car) == 180
    modes = {(("mode", k), ("vehicle_id", "car1")): v for k, v in m.mode_counts.items()}
    assert s["v2i_obu_mode_cycles_total"] == modes
    assert s["v2i_obu_fusion_mode"] == {(("mode", "intra"), ("vehicle_id", "car1")): 1.0}
    assert one(s, "v2i_obu_rejected_total", reason="stale", **car) == 4
    assert one(s, "v2i_obu_output_dropped_total", reason="too_many", **car) == 2
    rsu1 = {"rsu_id": "rsu1", **car}
    assert one(s, "v2i_obu_clock_offset_seconds", **rsu1) == pytest.approx(0.25)
    assert one(s, "v2i_obu_clock_offset_uncertainty_seconds", **rsu1) == pytest.approx(400e-6)
    assert one(s, "v2i_obu_clock_offset_naive_seconds", **rsu1) == pytest.approx(0.251)
    assert one(s, "v2i_obu_clock_drift_ratio", **rsu1) == pytest.approx(12e-6)
    assert one(s, "v2i_obu_clock_sync_samples_total", **rsu1) == 40
    assert one(s, "v2i_obu_clock_sync_outliers_total", **rsu1) == 2
    assert one(s, "v2i_obu_rsu_data_age_seconds", **rsu1) == pytest.approx(0.12)
    assert one(s, "v2i_obu_rsu_delay_p50_seconds", **rsu1) == pytest.approx(4.7e-3)
    assert one(s, "v2i_obu_rsu_delay_p95_seconds", **rsu1) == pytest.approx(7.9e-3)
    assert one(s, "v2i_obu_rsu_jitter_seconds", **rsu1) == pytest.approx(1.5e-3)
    assert one(s, "v2i_obu_rsu_loss_ratio", **rsu1) == pytest.approx(0.02)
    # the report's rsu_messages_received is the sum over RSUs; rsu2 has no clock estimate: no offset sample
    assert sum(s["v2i_obu_rsu_lists_accepted_total"].values()) == 98
    assert list(s["v2i_obu_clock_offset_seconds"]) == [tuple(sorted(rsu1.items()))]
    assert one(s, "v2i_obu_metrics_time_seconds", **car) == pytest.approx(T0 * 1e-9)


def test_before_the_first_metrics_only_the_latency_families_and_no_counts():
    node = SimpleNamespace(last_metrics=None, latency=StageLatency(), config=SimpleNamespace(vehicle_id="ego"))
    s = scrape(ObuCollector(node))
    assert not any(name.startswith("v2i_obu_cycles") for name in s)
    node.last_metrics = obu_metrics(vehicle_id="ego", cycles=1)  # read at scrape time, not at construction
    assert one(scrape(ObuCollector(node)), "v2i_obu_cycles_total", vehicle_id="ego") == 1


def test_stage_histograms_are_cumulative_with_the_latency_buckets_sum_and_count():
    values = {"rsu_to_obu": [0.0008, 0.0047, 0.0047, 0.012, 0.3], "fuse": [0.0011, 0.0021]}
    node = SimpleNamespace(last_metrics=obu_metrics(), latency=latency_with(values))
    s = scrape(ObuCollector(node))
    for stage, observed in values.items():
        labels = {"stage": stage, "vehicle_id": "car1"}
        buckets = {dict(k)["le"]: v for k, v in s["v2i_obu_stage_seconds_bucket"].items() if dict(k)["stage"] == stage}
        bounds = sorted(buckets, key=float)
        assert [float(b) for b in bounds] == [*BUCKETS_S, float("inf")]
        counts = [buckets[b] for b in bounds]
        assert counts == sorted(counts) and counts[-1] == len(observed)  # cumulative, +Inf = count
        for bound, count in zip(bounds, counts):
            assert count == sum(v <= float(bound) for v in observed)
        assert one(s, "v2i_obu_stage_seconds_count", **labels) == len(observed)
        assert one(s, "v2i_obu_stage_seconds_sum", **labels) == pytest.approx(sum(observed))
    # the rsu_to_obu stage is also the delay histogram, without a stage label
    delay = {dict(k)["le"]: v for k, v in s["v2i_obu_rsu_delay_seconds_bucket"].items()}
    assert delay == {dict(k)["le"]: v for k, v in s["v2i_obu_stage_seconds_bucket"].items()
                     if dict(k)["stage"] == "rsu_to_obu"}
    assert one(s, "v2i_obu_rsu_delay_seconds_count", vehicle_id="car1") == 5


def test_invalid_stage_durations_are_counted_by_stage():
    node = SimpleNamespace(last_metrics=None, latency=latency_with({"queue": [0.001, -0.002, float("nan")]}),
                           config=SimpleNamespace(vehicle_id="ego"))
    assert one(scrape(ObuCollector(node)), "v2i_obu_stage_invalid_total", stage="queue", vehicle_id="ego") == 2


def test_label_cap_admits_the_first_values_and_sums_the_rest_under_other():
    cap = LabelCap(max_values=3)
    assert [cap.label(v) for v in ("a", "b", None, "c", "a")] == ["a", "b", "", OTHER, "a"]
    assert cap.label("x" * 500) == OTHER  # past the cap; and a long value is cut before it is admitted
    assert LabelCap(2).label("y" * 500) == "y" * 64
    flood = {f"reason_{k:03d}": k for k in range(64)}
    counts = LabelCap(8).counts(flood)
    assert len(counts) == 9 and sum(counts.values()) == sum(flood.values())
    assert counts[OTHER] == sum(range(8, 64))  # sorted: the first eight admitted, the rest summed


def test_a_flood_of_rejection_reasons_gives_a_bounded_family_that_keeps_the_total():
    rejected = {f"bad_{k:02d}": 1 + k for k in range(63)}  # ObuMetrics allows 64 reasons
    collector = ObuCollector(SimpleNamespace(last_metrics=obu_metrics(rejected=rejected), latency=None))
    s = scrape(collector)
    assert len(s["v2i_obu_rejected_total"]) == 33
    assert sum(s["v2i_obu_rejected_total"].values()) == sum(rejected.values())
    # stable over scrapes: a reason admitted once keeps its series, a new one goes to _other
    more = {**rejected, "aaa_new": 5}
    collector.node.last_metrics = obu_metrics(rejected=more)
    again = scrape(collector)["v2i_obu_rejected_total"]
    assert set(again) == set(s["v2i_obu_rejected_total"])
    assert again[(("reason", OTHER), ("vehicle_id", "car1"))] == s["v2i_obu_rejected_total"][
        (("reason", OTHER), ("vehicle_id", "car1"))] + 5


def test_rsu_collector_reads_rsu_metrics_and_its_stages():
    perception = RsuPerception(frames=100, recall=0.9, precision=0.8)
    m = RsuMetrics(rsu_id="rsu7", t_ns=T0, published=99, skipped=1, time_replies=300, rejected={"too_large": 2},
                   perception=perception)
    s = scrape(RsuCollector(SimpleNamespace(last_metrics=m, latency=latency_with({"detect": [0.01], "put": [1e-4]}))))
    rsu = {"rsu_id": "rsu7"}
    assert one(s, "v2i_rsu_published_total", **rsu) == 99
    assert one(s, "v2i_rsu_skipped_total", **rsu) == 1
    assert one(s, "v2i_rsu_time_replies_total", **rsu) == 300
    assert one(s, "v2i_rsu_rejected_total", reason="too_large", **rsu) == 2
    assert one(s, "v2i_rsu_perception_frames_total", **rsu) == 100
    assert one(s, "v2i_rsu_perception_recall_ratio", **rsu) == pytest.approx(0.9)
    assert one(s, "v2i_rsu_stage_seconds_count", stage="detect", **rsu) == 1
    assert one(s, "v2i_rsu_stage_seconds_bucket", stage="put", le="0.0001", **rsu) == 1  # le: a bound counts in it


def test_link_collector_reads_the_relays_own_stats_snapshot():
    relay = LinkRelay(LinkConfig(link_id="l1", rsu_connect=EP, vehicle_connect=EP, profile="ideal",
                                 rsu_position=(0.0, 0.0)), SystemClock())
    pair = relay.pairs[0]
    pair.downlink.received, pair.downlink.delivered, pair.downlink.dropped = 10, 8, 2
    for delay_ms in (20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0, 90.0):
        pair.downlink.delay_ms.add(delay_ms)
    pair.uplink.received = pair.uplink.delivered = 4
    relay._gate.count("rate_limited")
    relay.last_stats = relay.stats_snapshot(T0)
    s = scrape(LinkCollector(relay))
    down, up = {"link_id": "l1", "direction": "downlink"}, {"link_id": "l1", "direction": "uplink"}
    assert (one(s, "v2i_link_received_total", **down), one(s, "v2i_link_delivered_total", **down),
            one(s, "v2i_link_dropped_total", **down)) == (10, 8, 2)
    assert one(s, "v2i_link_received_total", **up) == 4
    assert one(s, "v2i_link_delay_seconds_count", **down) == 8
    assert one(s, "v2i_link_delay_seconds_sum", **down) == pytest.approx(0.44)
    assert one(s, "v2i_link_delay_max_seconds", **down) == pytest.approx(0.09)
    assert one(s, "v2i_link_refused_total", link_id="l1", reason="rate_limited") == 1
    assert one(s, "v2i_link_profile_info", link_id="l1", profile="ideal") == 1
    assert one(s, "v2i_link_in_flight_messages", **up) == 0
    assert one(s, "v2i_link_pose_received_total", link_id="l1", vehicle_id="") == 0


def test_link_collector_in_v2v_mode_has_one_direction_and_poses_per_vehicle():
    vehicles = [{"vehicle_id": v, "connect": [f"tcp/127.0.0.1:{2000 + k}"]} for k, v in enumerate(("a", "b"))]
    relay = V2vRelay(LinkConfig(link_id="v2v", v2v=True, vehicles=vehicles, profile="ideal"), SystemClock())
    relay.pairs[("a", "b")].stats.received = 5
    relay.pairs[("b", "a")].stats.received = 2
    relay.last_stats = relay.stats_snapshot(T0)
    s = scrape(collector_for("link", relay))
    assert s["v2i_link_received_total"] == {(("direction", "v2v"), ("link_id", "v2v")): 7}
    assert set(s["v2i_link_pose_received_total"]) == {(("link_id", "v2v"), ("vehicle_id", v)) for v in "ab"}


def test_bucket_pairs_needs_one_count_per_bound_and_inf():
    pairs = bucket_pairs(list(range(len(BUCKETS_S) + 1)))
    assert pairs[0] == ("0.0001", 0.0) and pairs[-1] == ("+Inf", float(len(BUCKETS_S)))
    with pytest.raises(ValueError, match="cumulative counts"):
        bucket_pairs([0, 1])


def test_the_exporter_serves_metrics_and_refuses_a_port_in_use():
    assert serve(RsuCollector(SimpleNamespace()), 0) is None  # 0: off
    m = RsuMetrics(rsu_id="rsu1", t_ns=T0, published=5)
    server = serve(RsuCollector(SimpleNamespace(last_metrics=m, latency=None)), _free_port())
    try:
        body = urllib.request.urlopen(server.url, timeout=5).read().decode()
        assert 'v2i_rsu_published_total{rsu_id="rsu1"} 5.0' in body
        assert "process_resident_memory_bytes" in body
        with pytest.raises(MetricsPortError, match=f"--metrics-port {server.port}: cannot listen on 127.0.0.1"):
            MetricsServer(registry_for(RsuCollector(SimpleNamespace())), server.port)
    finally:
        server.close()


def test_an_unknown_service_has_no_collector():
    with pytest.raises(ValueError, match="no metrics collector"):
        collector_for("planner", SimpleNamespace())


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _every_series_name() -> set[str]:
    """Sample names of a scrape of each collector over nodes with every field and stage filled."""
    latency = latency_with({"rsu_to_obu": [0.01], "fuse": [0.001], "detect": [0.1], "relay_hold": [0.02]})
    relay = LinkRelay(LinkConfig(link_id="l1", rsu_connect=EP, vehicle_connect=EP, profile="ideal"), SystemClock())
    relay.pairs[0].downlink.delay_ms.add(25.0)
    relay.last_stats, relay.latency = relay.stats_snapshot(T0), latency
    rsu = RsuMetrics(rsu_id="rsu1", t_ns=T0, rejected={"x": 1})
    names: set[str] = set()
    for collector in (ObuCollector(SimpleNamespace(last_metrics=obu_metrics(), latency=latency)),
                      RsuCollector(SimpleNamespace(last_metrics=rsu, latency=latency)), LinkCollector(relay)):
        names |= set(scrape(collector))
    relay._gate.count("rate_limited")
    relay.last_stats = relay.stats_snapshot(T0)
    return names | set(scrape(LinkCollector(relay)))


def test_the_grafana_dashboard_queries_only_series_the_services_export():
    dashboard = json.loads((DEPLOY / "grafana" / "v2i-dashboard.json").read_text())
    exprs = [t["expr"] for p in dashboard["panels"] for t in p.get("targets", [])]
    used = {name for e in exprs for name in re.findall(r"\bv2i_[a-z0-9_]+", e)}
    assert len(exprs) >= 20 and {"v2i_obu_rsu_delay_seconds_bucket", "v2i_link_dropped_total"} <= used
    assert used - _every_series_name() == set()


def test_the_prometheus_config_scrapes_the_ports_the_demo_and_compose_use():
    config = yaml.safe_load((DEPLOY / "prometheus" / "prometheus.yml").read_text())
    targets = {job["job_name"]: job["static_configs"][0]["targets"] for job in config["scrape_configs"]}
    assert targets == {f"v2i-{svc}": [f"{svc}:{9101 + offset}"] for svc, offset in METRICS_PORT_OFFSETS.items()}
