"""``v2i fuzz`` against each live service: hostile traffic is refused and counted, the service
survives and keeps its normal output on time (a short run; the full one is in the README)."""

import pytest

from evaluation.fuzz_targets import TARGETS

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]


@pytest.mark.parametrize("target", sorted(TARGETS))
def test_a_service_survives_hostile_traffic_and_stays_on_time(target):
    report = TARGETS[target](1500, seed=3, rate_hz=1000.0).run()
    assert report["sent"] == 1500 and report["crashes"] == 0, report
    outputs = report["outputs"]
    if target.endswith("-inputs"):
        # every hostile input goes to the key the genuine sensor publishes on, at 1000/s: without
        # publisher authentication (issue 14) the key's rate limit refuses genuine frames too, so
        # some cycles go without fresh input; none may be late, and the refusals must show why
        assert outputs["late"] == 0 and outputs["missing"] <= outputs["expected"] // 2, outputs
        assert outputs["missing"] == 0 or report["rejected"].get("input_rate_limited", 0) > 0, report["rejected"]
    else:
        assert outputs["late"] == 0 and outputs["missing"] == 0, outputs
    assert report["rejected_total"] > 300, report["rejected"]
    assert report["rss_mb"]["growth"] < 20.0, report["rss_mb"]
    if target == "obu":
        assert report["forged_time_replies"] > 0
        assert report["clock"]["max_error_beyond_uncertainty_ms"] <= 0.0, report["clock"]
    if target == "rsu":
        assert report["probes"]["answered"] >= report["probes"]["sent"] - 2
    if target == "link":
        lists = report["genuine_lists"]
        assert lists["accepted_by_obu"] >= lists["published"] - 2, lists


def test_the_rsu_survives_hostile_frames_in_its_recording():
    from evaluation.fuzz_frames import FramesFuzz

    report = FramesFuzz(30, seed=3, rate_hz=20.0).run()
    assert report["sent"] == 30 and report["crashes"] == 0, report
    assert report["outputs"]["late"] == 0 and report["outputs"]["missing"] == 0, report["outputs"]
    assert report["rejected_total"] == 30, report["rejected"]  # every hostile file, and nothing genuine
    assert report["rss_mb"]["growth"] < 20.0, report["rss_mb"]
