"""Live: an RSU sending CPMs by TS 103 324's generation rules (--wire cpm --cpm-rules) through the link
emulator to a v2i OBU (rsu_service.cpm_rules, rsu_service.cpm_segments)."""

from __future__ import annotations

import pytest

from v2i.offline.spec import RunSpec
from v2i.orchestration.demo import Demo

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]


def test_an_rsu_under_the_cpm_rules_is_fused_through_the_emulator():
    demo = Demo(RunSpec(profile="ideal", seed=1, duration_s=8.0, wire="cpm", cpm_rules=True))
    report = demo.run()
    assert all(child.proc.poll() is not None for child in demo.children.values()), "a child outlived the demo"
    assert report["cpm_rules"] is True
    # 5 Hz events over 8 s; the runner's target moves > 4 m per 200 ms, so nearly every event sends a CPM
    assert report["rsu_messages_received"] >= 25, report["rsu_messages_received"]
    assert report["obu_rejected"].get("duplicate", 0) == 0, report["obu_rejected"]
    assert report["target"]["first_detection_distance_m"] > 60.0, report["target"]
