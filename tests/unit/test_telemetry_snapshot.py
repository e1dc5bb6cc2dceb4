"""v2i.telemetry.snapshot / windowed / link_view: ratios from cumulative counters, mode shares,
impairments in force, caps and hostile payloads."""

from __future__ import annotations

import json

import msgpack
import pytest

from schemas.codec import encode
from schemas.messages import ObuMetrics, RsuLinkStatus, RsuMetrics
from v2i.telemetry.snapshot import TelemetryBoard
from v2i.telemetry.windowed import WindowedCounters, shares

S = 1_000_000_000
T0 = 1_767_225_600 * S  # message stamps must be after 2000


def obu(t_s: float, cycles: int, out_miss: int, covered: int, rsu_miss: int, mode: str = "intra",
        modes: dict | None = None, vid: str = "ego", **extra) -> ObuMetrics:
    return ObuMetrics(vehicle_id=vid, t_ns=T0 + round(t_s * S), cycles=cycles, output_deadline_misses=out_miss,
                      covered_cycles=covered, rsu_deadline_misses=rsu_miss, mode=mode,
                      mode_counts=modes or {mode: cycles}, **extra)


def test_window_ratio_differs_from_run_ratio():
    """10 Hz for 30 s: no misses in the first 20 s, every second cycle missed in the last 10 s."""
    board = TelemetryBoard(window_s=10.0)
    misses = 0
    for k in range(1, 301):
        if k > 200 and k % 2 == 0:
            misses += 1
        board.on_obu_metrics(obu(k / 10, k, misses, k, 0), round(k / 10 * S))
    v = board.snapshot(round(30.0 * S))["vehicles"]["ego"]
    assert v["output_miss_ratio"]["run"] == round(50 / 300, 4)
    assert v["output_miss_ratio"]["window"] == 0.5  # cycles 201..300 over 10 s: 50 of 100
    assert v["window_span_s"] == pytest.approx(10.0, abs=0.11)
    assert v["rsu_miss_ratio"] == {"run": 0.0, "window": 0.0}


def test_rsu_miss_ratio_is_per_covered_cycle_and_none_before_any():
    board = TelemetryBoard()
    board.on_obu_metrics(obu(0.1, 1, 0, 0, 0), S)
    assert board.snapshot(S)["vehicles"]["ego"]["rsu_miss_ratio"] == {"run": None, "window": None}
    board.on_obu_metrics(obu(0.2, 10, 0, 4, 1), 2 * S)
    v = board.snapshot(2 * S)["vehicles"]["ego"]
    assert v["rsu_miss_ratio"]["run"] == 0.25
    assert v["rsu_miss_ratio"]["window"] == round(1 / 4, 4)  # increments 1 miss over 4 covered


def test_restart_starts_the_window_again():
    board = TelemetryBoard()
    board.on_obu_metrics(obu(1, 100, 50, 100, 0), 1 * S)
    board.on_obu_metrics(obu(2, 110, 55, 110, 0), 2 * S)
    board.on_obu_metrics(obu(3, 5, 0, 5, 0), 3 * S)  # the OBU restarted: counters from 0
    board.on_obu_metrics(obu(4, 15, 0, 15, 0), 4 * S)
    v = board.snapshot(4 * S)["vehicles"]["ego"]
    assert v["restarts"] == 1
    assert v["output_miss_ratio"] == {"run": 0.0, "window": 0.0}


def test_window_memory_is_bounded_under_a_flood():
    w = WindowedCounters(window_ns=10 * S, max_points=50)
    for k in range(100_000):  # 10 kHz for 10 s
        w.add(k * 100_000, {"cycles": k, "misses": k // 2})
    assert len(w) <= 52
    span_s, delta = w.delta()
    assert span_s == pytest.approx(10.0, abs=0.25)
    assert delta["misses"] / delta["cycles"] == pytest.approx(0.5, abs=0.01)


def test_mode_shares_run_and_window():
    board = TelemetryBoard(window_s=5.0)
    board.on_obu_metrics(obu(1, 10, 0, 10, 0, "intra", {"intra": 10}), 1 * S)
    board.on_obu_metrics(obu(7, 20, 0, 20, 0, "inter", {"intra": 10, "inter": 10}), 7 * S)
    board.on_obu_metrics(obu(8, 30, 0, 30, 0, "vehicle_only", {"intra": 10, "inter": 10, "vehicle_only": 10}), 8 * S)
    v = board.snapshot(8 * S)["vehicles"]["ego"]
    assert v["mode"] == "vehicle_only"
    assert v["mode_share"] == {"intra": 0.3333, "inter": 0.3333, "vehicle_only": 0.3333}
    assert v["mode_share_window"] == {"inter": 0.5, "vehicle_only": 0.5}  # base: the point at 1 s
    assert shares({}) == {} and shares({"a": 0}) == {}


def test_rsu_view_clock_and_latency_and_totals():
    status = RsuLinkStatus(rsu_id="rsu1", clock_offset_ns=25_400_000, clock_uncertainty_ns=300_000,
                           clock_drift_ppm=12.0, messages_accepted=42, last_data_age_ms=130.0,
                           delay_p50_ms=40.0, delay_p95_ms=80.0, loss_ratio=0.05)
    board = TelemetryBoard()
    board.on_obu_metrics(obu(1, 10, 1, 8, 2, rsus=(status,), rejected={"stale": 3}), S)
    board.on_obu_metrics(obu(1, 10, 0, 10, 0, vid="car2", mode="inter"), S)
    board.on_rsu_metrics(RsuMetrics(rsu_id="rsu1", t_ns=T0, published=90, skipped=10, rejected={"rate": 1}), S)
    snap = board.snapshot(3 * S)
    r = snap["vehicles"]["ego"]["rsus"]["rsu1"]
    assert (r["clock_offset_ms"], r["clock_uncertainty_ms"], r["delay_p95_ms"]) == (25.4, 0.3, 80.0)
    assert snap["vehicles"]["ego"]["rejected"] == {"stale": 3}
    assert snap["vehicles"]["ego"]["latency_ms"] is None
    assert snap["vehicles"]["ego"]["age_s"] == 2.0
    assert snap["rsus"]["rsu1"]["skipped_ratio"] == 0.1
    t = snap["totals"]
    assert (t["vehicles"], t["cycles"], t["output_deadline_misses"], t["rsu_lists_received"]) == (2, 20, 1, 42)
    assert t["output_miss_ratio"]["run"] == 0.05 and t["rsu_miss_ratio"]["run"] == round(2 / 18, 4)
    assert t["modes"] == {"intra": 1, "inter": 1}
    json.dumps(snap)  # JSON-ready
    timed = obu(2, 11, 1, 9, 2, latency_ms={"fuse": {"count": 5, "p50": 1.0, "p95": 2.0, "p99": 3.0}})
    board.on_obu_metrics(timed, 2 * S)
    assert board.snapshot(3 * S)["vehicles"]["ego"]["latency_ms"] == {
        "fuse": {"count": 5, "p50": 1.0, "p95": 2.0, "p99": 3.0}}


def stats(t_s: float, recv: int, dropped: int, recent=(), link_id: str = "link1", **extra) -> bytes:
    return json.dumps({"link_id": link_id, "time_ns": round(t_s * S), "profile": "lte-v2x",
                       "downlink": {"received": recv, "delivered": recv - dropped, "dropped": dropped,
                                    "delay_ms": {"count": recv, "mean": 30.0, "min": 10.0, "max": 90.0}},
                       "uplink": {"received": 0, "delivered": 0, "dropped": 0, "delay_ms": {"count": 0}},
                       "control": {"applied": len(recent), "rejected": {}, "recent": list(recent)},
                       **extra}).encode()


def test_link_drop_ratios_and_impairments_in_force():
    board = TelemetryBoard(window_s=10.0)
    outage = {"seq": 1, "result": "outage on both for 3 s"}
    assert board.on_sample("v2x/link/link1/stats", stats(1, 100, 0), S) == "link_stats"
    board.on_sample("v2x/link/link1/stats", stats(2, 110, 0, [outage]), 2 * S)
    board.on_sample("v2x/link/link1/stats", stats(3, 120, 10, [outage]), 3 * S)
    link = board.snapshot(3 * S)["links"]["link1"]
    assert link["directions"]["downlink"]["drop_ratio"] == round(10 / 120, 4)
    assert link["drop_ratio_window"]["downlink"] == 0.5  # 10 of the 20 since the first stats
    assert link["directions"]["uplink"]["drop_ratio"] is None
    assert link["impairments"] == [{"effect": "outage on both", "left_s": 2.0}]
    assert link["latency_ms"] is None
    board.on_sample("v2x/link/link1/stats", stats(5, 120, 10, [outage]), 5 * S)  # window over at 2 + 3 s
    assert board.snapshot(5 * S)["links"]["link1"]["impairments"] == []
    spike = {"seq": 2, "result": "+200 ms on downlink for 10 s"}
    board.on_sample("v2x/link/link1/stats", stats(6, 130, 10, [outage, spike]), 6 * S)
    assert board.snapshot(6 * S)["links"]["link1"]["impairments"][0]["effect"] == "+200 ms on downlink"
    cleared = {"seq": 3, "result": "impairments cleared"}
    board.on_sample("v2x/link/link1/stats", stats(7, 140, 10, [outage, spike, cleared]), 7 * S)
    assert board.snapshot(7 * S)["links"]["link1"]["impairments"] == []


def test_caps_count_what_is_ignored():
    board = TelemetryBoard(max_nodes=3)
    for k in range(10):
        board.on_sample(f"v2x/obu/car{k}/metrics", encode(obu(1, 1, 0, 0, 0, vid=f"car{k}")), S)
        board.on_sample(f"v2x/rsu/r{k}/metrics", encode(RsuMetrics(rsu_id=f"r{k}", t_ns=T0)), S)
        board.on_sample(f"v2x/link/l{k}/stats", stats(1, 1, 0, link_id=f"l{k}"), S)
    snap = board.snapshot(S)
    assert (len(snap["vehicles"]), len(snap["rsus"]), len(snap["links"])) == (3, 3, 3)
    assert snap["intake"]["ignored"] == {"vehicles_over_cap": 7, "rsus_over_cap": 7, "links_over_cap": 7}
    board.on_sample("v2x/obu/car0/metrics", encode(obu(2, 2, 0, 0, 0, vid="car0")), 2 * S)  # tracked: still taken
    assert board.snapshot(2 * S)["vehicles"]["car0"]["cycles"] == 2


HOSTILE = [
    ("v2x/obu/ego/metrics", b""),
    ("v2x/obu/ego/metrics", b"\xff" * 100),
    ("v2x/obu/ego/metrics", msgpack.packb({"type": "obu_metrics", "v": 1, "body": {"cycles": -1}})),
    ("v2x/obu/ego/metrics", encode(RsuMetrics(rsu_id="r1", t_ns=T0))),  # the wrong type
    ("v2x/rsu/r1/metrics", b"{}"),
    ("v2x/link/l1/stats", b"not json"),
    ("v2x/link/l1/stats", b"[1, 2]"),
    ("v2x/link/l1/stats", b"[" * 100_000),
    ("v2x/link/l1/stats", b"{\"link_id\": \"../x\"}"),
    ("v2x/link/l1/stats", b"{\"link_id\": \"l1\"" + b" " * (2 << 20) + b"}"),
    ("v2x/link/l1/stats", b"\xc3\x28"),
]


def test_hostile_payloads_are_counted_never_raised():
    board = TelemetryBoard()
    for key, payload in HOSTILE:
        assert board.on_sample(key, payload, S) == "undecodable"
    assert sum(board.snapshot(S)["intake"]["undecodable"].values()) == len(HOSTILE)
    assert board.snapshot(S)["vehicles"] == {} and board.snapshot(S)["links"] == {}


def test_hostile_fields_in_valid_link_stats_read_as_absent():
    board = TelemetryBoard()
    weird = json.dumps({"link_id": "l1", "time_ns": "soon", "profile": ["x"], "downlink": {"received": -5,
                        "dropped": True, "delay_ms": {"mean": "NaN"}}, "uplink": 7, "refused": {"a": "b", "c": 2},
                        "control": {"recent": [None, 3, {"seq": "x", "result": "outage on both for nan s"},
                                               {"seq": 9, "result": "loss 1 on both for 1e999 s"},
                                               {"seq": 8, "result": "x for . s"}]},
                        "pairs": [1, {"vehicle_id": 5}],
                        "latency_ms": {"relay_hold": {"count": 3, "p50": 1.5, "p95": "x"}, "bad": 4}}).encode()
    assert board.on_sample("v2x/link/l1/stats", weird, S) == "link_stats"
    link = board.snapshot(S)["links"]["l1"]
    assert link["directions"]["downlink"]["received"] is None and "uplink" not in link["directions"]
    assert link["refused"] == {"c": 2} and link["profile"] is None and link["impairments"] == []
    assert link["pairs"] == [{"vehicle_id": None, "profile": None}]
    assert link["latency_ms"] == {"relay_hold": {"count": 3, "p50": 1.5, "p95": None, "p99": None}}
    json.dumps(link, allow_nan=False)


def test_keys_that_are_not_metrics_or_disagree_with_the_id():
    board = TelemetryBoard()
    assert board.on_sample("v2x/obu/ego/objects", b"", S) == "ignored"
    assert board.on_sample("v2x/obu/a/b/metrics", b"", S) == "ignored"
    assert board.on_sample("v2x/obu/other/metrics", encode(obu(1, 1, 0, 0, 0)), S) == "ignored"
    assert board.snapshot(S)["intake"]["ignored"] == {"other_key": 2, "id_mismatch": 1}
