"""``v2i demo`` of a site: connected-intersection's 2 RSUs, 2 link emulators and 3 OBUs as
real OS processes on loopback Zenoh (``v2i.orchestration.site_demo``), scored per vehicle.

One short run: every vehicle publishes and is scored, every OBU hears both RSUs through
its own channels, the report has the offline runner's keys, no child outlives the demo. The
site signs as ``v2i demo`` does by default (``security="strict"``): every RSU signs, every OBU
verifies against the site PKI and drops nothing genuine.
"""

from __future__ import annotations

import os

import pytest

from v2i.offline.runner import OfflineRun
from v2i.orchestration.site_demo import SiteDemo, is_site
from v2i.offline.spec import RunSpec
from v2i.sim.scenario import load_scenario
from v2i.cli import main

pytestmark = [pytest.mark.integration, pytest.mark.timeout(150)]

SPEC = RunSpec(scenario="connected-intersection", profile="lte-v2x", seed=0, duration_s=9.0, security="strict")


@pytest.fixture(scope="module")
def demo() -> SiteDemo:
    demo = SiteDemo(SPEC)
    demo.report = demo.run()
    return demo


def test_every_node_ran_as_its_own_process(demo):
    assert sorted(demo.children) == ["link-rsu-nw", "link-rsu-se", "link-v2v", "obu car-2", "obu car-3", "obu ego",
                                     "rsu rsu-nw", "rsu rsu-se"]  # link-v2v: the scenario's V2V
    assert len({child.proc.pid for child in demo.children.values()}) == 8


def test_vehicles_share_through_the_v2v_emulator(demo):
    pairs = demo.report["v2v_link"]["pairs"]
    assert sorted(pairs) == sorted(f"{a}>{b}" for a in ("ego", "car-2", "car-3") for b in ("ego", "car-2", "car-3")
                                   if a != b)
    assert all(p["delivered"] > 0 and p["distance_m"] is not None for p in pairs.values()), pairs
    for name, scores in demo.report["vehicles"].items():
        assert sorted(scores["peers"]) == sorted({"ego", "car-2", "car-3"} - {name}), name
        assert all(p["lists_accepted"] > 0 and p["sync_samples"] > 0 for p in scores["peers"].values()), name


def test_the_run_started_once_all_eight_were_ready(demo):
    startup = demo.report["startup"]
    assert startup["ready_s"] > 0
    ahead = startup["started_ahead_ms"]  # the emulators need no time zero
    assert sorted(ahead) == ["obu car-2", "obu car-3", "obu ego", "rsu rsu-nw", "rsu rsu-se"]
    assert all(ms > 0 for ms in ahead.values()), ahead  # each began before time zero


def test_no_child_outlives_the_demo(demo):
    for name, child in demo.children.items():
        assert child.proc.poll() is not None, f"{name} still runs"
        with pytest.raises(ProcessLookupError):  # reaped: the pid names no process of ours any more
            os.kill(child.proc.pid, 0)


def test_every_vehicle_is_scored_with_lists_from_both_rsus(demo):
    vehicles = demo.report["vehicles"]
    assert sorted(vehicles) == ["car-2", "car-3", "ego"]
    for name, scores in vehicles.items():
        assert scores["cycles"] == 90, name
        assert scores["outputs"] > 0.9 * scores["cycles"], name  # published cycles the watcher scored
        # subscribed before time zero, the watcher heard every output the OBU says it published
        assert demo.report["obu_output_deadline_misses"][name]["cycles"] == scores["outputs"], name
        accepted = demo.report["rsu_lists_accepted"][name]
        assert sorted(accepted) == ["rsu-nw", "rsu-se"], name
        assert min(accepted.values()) > 0, f"{name} heard {accepted}"
    # each OBU senses as its own vehicle: car-3 faces the runner's approach and its own LiDAR
    # sees it from t = 4.5 s; the ego's LiDAR only from t = 10 s (offline, 9 s: 44 and 0 cycles)
    assert vehicles["car-3"]["vehicle_only"]["detected_cycles"] > 20
    assert vehicles["ego"]["vehicle_only"]["detected_cycles"] == 0
    assert vehicles["ego"]["target"]["detected_cycles"] > 0  # through the RSUs only


def test_every_rsu_signs_and_every_obu_verifies_without_a_drop(demo):
    for name, child in demo.children.items():
        if name.startswith(("rsu ", "obu ")):
            assert child.argv[child.argv.index("--pki") + 1] == str(demo.pki_dir), name
        if name.startswith("obu "):
            assert child.argv[child.argv.index("--security") + 1] == "strict", name
    assert sorted(demo.obu_rejected) == ["car-2", "car-3", "ego"]  # every OBU's metrics were heard
    assert demo.report["security_outcomes"] == {"car-2": {}, "car-3": {}, "ego": {}}, demo.obu_rejected


def test_each_rsu_reports_its_perception(demo):
    rsus = demo.report["rsus"]
    assert sorted(rsus) == ["rsu-nw", "rsu-se"]
    for rsu_id, perception in rsus.items():
        assert perception["frames"] > 0, rsu_id


def test_report_has_the_offline_runners_keys(demo):
    run = OfflineRun(SPEC)
    run.execute()
    offline = run.report()
    assert set(offline) <= set(demo.report)
    assert set(offline["vehicles"]) == set(demo.report["vehicles"])
    for name, scores in offline["vehicles"].items():
        assert set(scores) == set(demo.report["vehicles"][name]), name
    assert set(offline["rsus"]["rsu-se"]) == set(demo.report["rsus"]["rsu-se"])
    assert demo.report["driver"] == "demo"


def test_site_scenarios_are_told_apart():
    assert is_site(load_scenario("connected-intersection"))
    assert is_site(load_scenario("two-rsu-corridor"))
    assert not is_site(load_scenario("red-light-runner"))


@pytest.mark.parametrize("argv", [["demo", "--kill-link-at", "2"], ["demo", "--fusion", "roif"]])
def test_single_link_options_are_refused_on_a_site(argv, capsys):
    assert main([*argv[:1], "--scenario", "connected-intersection", *argv[1:]]) == 2
    assert "several" in capsys.readouterr().err
