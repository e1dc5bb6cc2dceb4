"""``v2i attack``'s opt-in kinds (issue 32) against a strict site on plain ``tcp/`` loopback endpoints.

RSU (clock 350 ms ahead, 60 ppm), OBU (``--security strict``, told its RSU) and an lte-v2x link
emulator, as the README's two-host recipe starts them, and an attacker holding no key of the
genuine RSU's:

1. ``time_doubled --from-start``: started before the site's start line, it relays the OBU's time
   queries to the RSU and returns each genuine signed reply twice; the OBU must still get its
   clock within 3 s of time zero, fuse RSU data in most cycles and confirm no step;
2. ``flood`` at 500 msg/s on the genuine RSU's own objects key: every flood message refused for its
   reason, no ghost, no output miss, and the genuine RSU's lists still accepted.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from v2i.orchestration.children import READY_TIMEOUT_S, Child, start_all, wait_ready
from v2i.runtime.transport import free_tcp_endpoint
from v2i.security.attacker_keys import prepare_attacker_pki
from v2i.security.site import write_site

DOUBLED_S, FLOOD_S, FLOOD_HZ = 8.0, 6.0, 500.0
RUN_S = 300.0  # the services' --duration: they are stopped when the attacks are done
V2I = [sys.executable, "-m", "v2i"]
pytestmark = [pytest.mark.integration, pytest.mark.timeout(2 * READY_TIMEOUT_S + 240)]


def _site(pki: Path) -> tuple[list[Child], str, str]:
    rsu_ep, obu_ep = free_tcp_endpoint(), free_tcp_endpoint()
    common = ["--await-start", "--pki", str(pki), "--duration", f"{RUN_S:g}"]
    children = [
        Child("rsu", V2I + ["rsu", "--listen", rsu_ep, *common, "--clock-offset-ms", "350", "--clock-drift-ppm", "60"]),
        Child("obu", V2I + ["obu", "--listen", obu_ep, *common, "--security", "strict", "--known-rsus", "rsu1"]),
        Child("link", V2I + ["link", "--rsu-connect", rsu_ep, "--vehicle-connect", obu_ep, "--profile", "lte-v2x",
                             "--pki", str(pki), "--duration", f"{RUN_S:g}"]),
    ]
    return children, rsu_ep, obu_ep


def _attack(rsu_ep: str, obu_ep: str, pki: Path, report: Path, *options: str) -> list[str]:
    return V2I + ["attack", "--connect", obu_ep, "--sniff", rsu_ep, "--pki", str(pki), "--warmup-s", "1",
                  "--settle-s", "1", "--json", str(report), *options]


def test_doubled_time_replies_and_a_flood_on_the_genuine_key_cost_the_genuine_rsu_nothing(tmp_path: Path) -> None:
    pki = tmp_path / "pki"
    write_site(pki, time.time_ns(), rsu_ids=["rsu1"], vehicle_ids=["ego"])
    prepare_attacker_pki(pki, time.time_ns(), "rsu1")
    children, rsu_ep, obu_ep = _site(pki)
    report_json = tmp_path / "attack.json"
    attack = None
    try:
        wait_ready(children)
        attack = Child("attack", _attack(rsu_ep, obu_ep, pki, report_json, "--kinds", "time_doubled,flood",
                                         "--from-start", "--time-s", f"{DOUBLED_S:g}", "--flood-rate-hz",
                                         f"{FLOOD_HZ:g}", "--flood-s", f"{FLOOD_S:g}"))
        wait_ready([attack])  # its queryable is declared: it meets the OBU's first time query
        start_ns = start_all(children)
        attack.proc.wait(timeout=READY_TIMEOUT_S + 120)
        for child in children:
            assert child.proc.poll() is None, f"{child.name} exited with {child.proc.returncode}{child.tail()}"
    finally:
        if attack is not None:
            attack.stop()
        for child in children:
            child.stop()
    assert report_json.exists(), attack.tail()
    report = json.loads(report_json.read_text())
    summary = json.dumps(report["kinds"], indent=1)[:3000]
    doubled, flood = report["kinds"]["time_doubled"], report["kinds"]["flood"]
    first_sample_ns = doubled["clock_samples"][0][0]
    assert (first_sample_ns - start_ns) / 1e9 <= 3.0, summary  # synchronised within 3 s of time zero
    assert doubled["relay"]["returned"] == 2 * doubled["relay"]["rsu_replies"] > 0, summary
    assert doubled["clock_steps"] == 0 and doubled["tracking_share"] >= 0.8, summary
    assert abs(doubled["clock_samples"][-1][1] - 350e6) < 20e6, summary  # 350 ms + 60 ppm x seconds
    # every flood message refused: by the verifier for its reason, or before it by the intake (counted)
    assert flood["sent"] >= 0.8 * FLOOD_HZ * FLOOD_S, summary
    assert flood["rejected_as_intended"] == flood["rejected_total"], summary
    assert flood["rejected_total"] + sum(flood["other_refusals"].values()) >= flood["sent"], summary
    assert not flood["accepted"] and flood["ghost_outputs"] == 0 and flood["output_deadline_misses"] == 0, summary
    assert flood["genuine_sent"] >= 0.8 * 5 * FLOOD_S, summary  # the RSU's 5 lists/s were on the air
    assert flood["genuine_accepted"] >= 0.9 * flood["genuine_sent"], summary
