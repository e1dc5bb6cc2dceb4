"""``v2i fuzz`` against each live service: hostile traffic is refused and counted, the service
survives and keeps its normal output on time (a short run; the full one is in the README)."""

import pytest

from v2i.orchestration.children import READY_TIMEOUT_S
from v2i.adversary.fuzz_targets import TARGETS

pytestmark = [pytest.mark.integration, pytest.mark.timeout(READY_TIMEOUT_S + 120)]
# Outputs past their deadline a busy machine causes without any hostile input: with two busy loops on the
# 2 cores (load ~12) the fuzzed OBU of obu-inputs was late 3 times in 26 cycles. A service that hostile
# input stalls is late or missing for most of the window (1.5 s of fuzzing, 15 cycles).
LATE_SHARE = 0.2


# the RSU publishes at 5 Hz: 1.5 s of fuzzing is 7 lists, too few for a share of missing ones (under
# two busy loops 0-4 of 7 missing, the limit 3); 3 s gives 14 (3-5 missing measured, the limit 7)
MESSAGES = {"rsu-inputs": 3000}


@pytest.mark.parametrize("target", sorted(TARGETS))
def test_a_service_survives_hostile_traffic_and_stays_on_time(target):
    n = MESSAGES.get(target, 1500)
    report = TARGETS[target](n, seed=3, rate_hz=1000.0).run()
    assert report["sent"] == n and report["crashes"] == 0, report
    outputs = report["outputs"]
    if target.endswith("-inputs"):
        # every hostile input goes to the key the genuine sensor publishes on, at 1000/s: without
        # publisher authentication (issue 14) the key's rate limit refuses genuine frames too, so
        # some cycles go without fresh input; none may be late, and the refusals must show why
        assert outputs["late"] <= LATE_SHARE * outputs["expected"] and outputs["missing"] <= outputs["expected"] // 2, outputs
        assert outputs["missing"] == 0 or report["rejected"].get("input_rate_limited", 0) > 0, report["rejected"]
    else:
        assert outputs["late"] <= LATE_SHARE * outputs["expected"] and outputs["missing"] == 0, outputs
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
    from v2i.adversary.fuzz_frames import FramesFuzz

    # 5 frames/s: with two busy loops on the 2 cores (load 13-14) the RSU read all 70 files at 5 Hz; at 20 Hz it
    # let 32-48 of their capture times pass (skipped: it publishes only what is current)
    report = FramesFuzz(30, seed=3, rate_hz=5.0).run()
    outputs = report["outputs"]
    assert report["sent"] == 30 and report["crashes"] == 0, report
    assert outputs["missing"] == 0, outputs  # every file published, or its time passed (skipped)
    # every hostile file the RSU read is refused, and nothing genuine; a skipped one is not read: at least half
    # are read, a margin for a machine busier still
    assert report["rejected_total"] == report["hostile_read"] >= 15, report
    assert report["hostile_late"] == 0, report  # refusing a file never holds the RSU up
    # the genuine frames among them go on being published (a genuine frame's detection on a loaded machine can
    # take over 250 ms: late 7 of 68 lists at load ~14, so lateness is the hostile files' only, above)
    assert outputs["received"] >= outputs["expected"] // 2, outputs
    assert report["rss_mb"]["growth"] < 20.0, report["rss_mb"]
