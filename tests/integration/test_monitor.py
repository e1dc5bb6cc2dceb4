"""``v2i monitor --once --json -`` against a live demo (RSU, link emulator, OBU as processes),
with a chaos delay spike in force, and the demo's live line on a non-terminal stderr."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import pytest

from evaluation.chaos import ChaosEvent, ChaosTimeline, DelaySpike
from evaluation.demo import Demo
from evaluation.spec import RunSpec

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]


def test_monitor_snapshot_of_a_live_demo(capfd):
    timeline = ChaosTimeline(name="spike", events=[ChaosEvent(at_s=0.5, delay_spike=DelaySpike(duration_s=20.0, extra_ms=50.0))])
    demo = Demo(RunSpec(profile="lte-v2x", seed=1, duration_s=9.0), chaos=timeline, progress="v2i demo")
    result: dict = {}
    runner = threading.Thread(target=lambda: result.update(demo.run()), daemon=True)
    runner.start()
    try:
        # waits for the services (startup 10 s), then for metrics or stats from each endpoint
        out = subprocess.run([sys.executable, "-m", "v2i", "monitor", "--connect", demo.obu_ep, "--connect", demo.rsu_ep,
                              "--connect", demo.control_ep, "--once", "--json", "-", "--timeout", "20"],
                             capture_output=True, text=True, timeout=60, check=False)
    finally:
        runner.join(80)
    assert out.returncode == 0, out.stderr
    snap = json.loads(out.stdout)
    assert set(snap) == {"window_s", "totals", "vehicles", "rsus", "links", "intake", "sources"}
    vehicle = snap["vehicles"]["ego"]
    for key in ("output_miss_ratio", "rsu_miss_ratio", "mode", "mode_share", "rsus", "rejected", "latency_ms"):
        assert key in vehicle
    assert vehicle["cycles"] > 0 and set(vehicle["output_miss_ratio"]) == {"run", "window"}
    rsu = vehicle["rsus"]["rsu1"]
    for key in ("delay_p50_ms", "delay_p95_ms", "loss_ratio", "data_age_ms", "clock_offset_ms", "clock_uncertainty_ms"):
        assert key in rsu
    assert snap["rsus"]["rsu1"]["published"] > 0
    link = snap["links"]["link1"]
    assert link["profile"] == "lte-v2x" and link["directions"]["downlink"]["received"] > 0
    if link["controls_applied"]:  # the spike was applied before this stats message
        assert link["impairments"][0]["effect"].startswith("+50 ms")
    assert all(s["connected"] and s["metrics_messages"] > 0 for s in snap["sources"])
    assert result["cycles"] == 90  # the demo ran to its end with the monitor attached
    err = capfd.readouterr().err
    assert "endpoints: OBU" in err and "v2i demo " in err and "misses: output" in err
    assert "\r" not in err  # not a terminal: plain lines
