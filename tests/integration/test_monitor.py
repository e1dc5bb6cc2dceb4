"""``v2i monitor --once --json -`` against a live demo (RSU, link emulator, OBU as processes),
with a chaos delay spike in force, and the demo's live line on a non-terminal stderr.

A snapshot may come before the OBU accepted its first RSU list (``rsu_heard`` false, ``rsus``
empty) or before the link relayed anything: valid, and said so. The test asks again (each --once
a fresh process) until what it checks has happened, within SNAPSHOT_DEADLINE_S, while the demo
runs; a machine under load needs the long start-up bound (MONITOR_TIMEOUT_S)."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time

import pytest

from v2i.offline.chaos import ChaosEvent, ChaosTimeline, DelaySpike
from v2i.orchestration.demo import Demo
from v2i.offline.spec import RunSpec

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]

DURATION_S = 15.0  # long enough for a second --once on a loaded machine
MONITOR_TIMEOUT_S = 90.0  # the first --once waits for the services' first metrics (start-up under load)
SNAPSHOT_DEADLINE_S = 150.0
KEYS = {"window_s", "totals", "vehicles", "rsus", "links", "intake", "sources"}


def _snapshot(demo: Demo) -> dict:
    out = subprocess.run([sys.executable, "-m", "v2i", "monitor", "--connect", demo.obu_ep, "--connect", demo.rsu_ep,
                          "--connect", demo.control_ep, "--once", "--json", "-", "--timeout", str(MONITOR_TIMEOUT_S)],
                         capture_output=True, text=True, timeout=MONITOR_TIMEOUT_S + 30, check=False)
    assert out.returncode == 0, out.stderr
    snap = json.loads(out.stdout)
    assert set(snap) == KEYS
    for v in snap["vehicles"].values():  # valid before any RSU is heard, and says so
        assert v["rsu_heard"] == bool(v["rsus"])
    assert snap["totals"]["vehicles_hearing_no_rsu"] == sum(not v["rsu_heard"] for v in snap["vehicles"].values())
    return snap


def _traffic_seen(snap: dict) -> bool:
    """The OBU heard rsu1, the RSU published and the link relayed downlink: what the test reads."""
    ego, link = snap["vehicles"].get("ego"), snap["links"].get("link1")
    return (ego is not None and "rsu1" in ego["rsus"] and snap["rsus"].get("rsu1", {}).get("published", 0) > 0
            and link is not None and link["directions"]["downlink"]["received"] > 0)


def test_monitor_snapshot_of_a_live_demo(capfd):
    timeline = ChaosTimeline(name="spike", events=[ChaosEvent(at_s=0.5, delay_spike=DelaySpike(duration_s=20.0, extra_ms=50.0))])
    demo = Demo(RunSpec(profile="lte-v2x", seed=1, duration_s=DURATION_S), chaos=timeline, progress="v2i demo")
    result: dict = {}
    runner = threading.Thread(target=lambda: result.update(demo.run()), daemon=True)
    runner.start()
    snaps: list[dict] = []
    try:
        deadline = time.monotonic() + SNAPSHOT_DEADLINE_S
        while runner.is_alive() and time.monotonic() < deadline and not (snaps and _traffic_seen(snaps[-1])):
            snaps.append(_snapshot(demo))
    finally:
        runner.join(SNAPSHOT_DEADLINE_S)
    assert snaps and _traffic_seen(snaps[-1]), f"{len(snaps)} snapshots, the last: {snaps[-1] if snaps else None}"
    snap = snaps[-1]
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
    assert result["cycles"] == round(DURATION_S * 10)  # the demo ran to its end with the monitor attached
    err = capfd.readouterr().err
    assert "endpoints: OBU" in err and "v2i demo " in err and "misses: output" in err
    assert "\r" not in err  # not a terminal: plain lines
