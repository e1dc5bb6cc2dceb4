"""The three services as real OS processes on loopback Zenoh, orchestrated by ``v2i demo``.

One short run in which the link emulator is killed and restarted: the OBU must publish
every cycle throughout, fall back to vehicle-only, fuse again afterwards, and the fused
output must see the red-light runner far earlier than the vehicle alone.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from v2i.orchestration.demo import Demo, LinkOutage
from v2i.reports.run_arrays import chaos_spans
from v2i.reports.run_report import write_demo_report
from v2i.offline.spec import RunSpec, summary

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]


@pytest.fixture(scope="module")
def finished() -> tuple[Demo, dict]:
    demo = Demo(RunSpec(profile="lte-v2x", seed=1, duration_s=12.0), outage=LinkOutage(at_s=1.5, down_s=3.0))
    result = demo.run()
    assert all(child.proc.poll() is not None for child in demo.children.values()), "a child outlived the demo"
    return demo, result


@pytest.fixture(scope="module")
def report(finished) -> dict:
    return finished[1]


def test_run_report_pictures(finished, tmp_path):
    """What ``v2i demo --report DIR`` writes after this run: the PNGs, the report, the kill shaded."""
    demo, result = finished
    written = write_demo_report(tmp_path / "report", result, demo)
    assert [p.name for p in written] == ["timeline.png", "bev.png", "report.json"]
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in written[:2])
    assert json.loads(written[2].read_text()) == result
    spans = chaos_spans(demo.chaos, demo.duration_s, [(p.fired_s, p.event) for p in demo.played])
    assert [s.kind for s in spans] == ["kill", "restart"] and spans[0].to_s == spans[1].from_s
    (rsu,) = demo.record.links.per_rsu()  # one sample per OBU metrics message (one per cycle)
    assert len(rsu.t_ns) >= 100 and np.isfinite(rsu.offset_ns).sum() >= 100


def test_every_cycle_is_published(report):
    assert report["cycles"] == 120
    assert report["outputs"] == report["cycles"]


def test_outage_falls_back_to_vehicle_only_and_recovers(report):
    outage = report["link_outage"]
    assert outage["cycles_published_during"] == outage["cycles_expected_during"] == 30
    # RSU frames stay usable for inter-frame fusion 0.6 s after the last one; then the RSU's
    # 5 s paths go to the planner (planning fusion) or, without them, vehicle-only
    share = outage["mode_share_during"]
    assert share["intra"] + share["inter"] <= 0.4
    assert share["planning"] + share["vehicle_only"] >= 0.6
    assert outage["fused_again_after_s"] is not None and outage["fused_again_after_s"] < 3.0


def test_v2i_sees_the_runner_much_earlier(report):
    fused = report["target"]["first_detection_distance_m"]
    own = report["vehicle_only"]["first_detection_distance_m"]
    assert own is not None and fused is not None
    assert fused >= 3 * own
    assert report["clock_offset_error_ms"]["samples"] > 0


def test_the_run_started_once_every_service_was_ready(report):
    startup = report["startup"]
    assert startup["ready_s"] > 0 and startup["lead_s"] > 0
    ahead = startup["started_ahead_ms"]
    assert set(ahead) == {"rsu", "obu"}  # the emulator needs no time zero
    assert all(0 < ms <= startup["lead_s"] * 1000 for ms in ahead.values()), ahead  # each began before time zero


def test_the_monitor_heard_every_output_the_obu_published(report):
    """The monitor subscribes before time zero, so its count of outputs is the OBU's own: the report's
    output misses (an expected cycle without an on-time output heard) are the OBU's late cycles, which
    the OBU also counts when the interval between two outputs runs over."""
    own = report["obu_output_deadline_misses"]["ego"]
    assert own["cycles"] == report["outputs"] == report["cycles"]
    assert report["output_deadline_miss_ratio"] <= own["ratio"]
    assert f"(the OBU's own count: {own['misses']} of {own['cycles']} late)" in summary(report)
