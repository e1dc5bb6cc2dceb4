"""A live demo recorded to MCAP (``Demo(record_to=...)``), then replayed into a fresh OBU
(``ReplayDemo``): the replayed OBU must see what the live one saw and score alike. The live run
signs (``security="strict"``, as ``v2i demo`` does by default): the recording keeps the envelopes
and the replay republishes their payloads unsigned."""

from __future__ import annotations

import pytest

from evaluation.demo import Demo
from evaluation.replay_demo import ReplayDemo
from evaluation.spec import RunSpec
from telemetry.mcap_reader import Recording

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[dict, dict, Recording]:
    path = tmp_path_factory.mktemp("record") / "run.mcap"
    spec = RunSpec(profile="lte-v2x", seed=1, duration_s=8.0, security="strict")
    live = Demo(spec, record_to=str(path)).run()
    replayed = ReplayDemo(str(path)).run()
    return live, replayed, Recording(path)


def test_the_recording_has_both_sides_the_clock_and_the_spec(runs):
    _, _, recording = runs
    assert {"rsu", "vehicle", "link"} <= set(recording.sides)
    keys = {(c.side, c.key) for c in recording.channels.values()}
    assert ("rsu", "v2x/rsu/rsu1/objects") in keys and ("vehicle", "v2x/rsu/rsu1/objects") in keys
    assert ("vehicle", "v2x/obu/ego/objects") in keys
    assert len(recording.exchanges()["rsu1"]) >= 50  # ~10 Hz from before the start to the end
    assert recording.metadata["run"]["duration_s"] == "8.0"
    signed = {(c.side, c.key) for c in recording.channels.values() if c.signed}
    assert ("vehicle", "v2x/rsu/rsu1/objects") in signed and ("rsu", "v2x/rsu/rsu1/time") in signed


def test_every_recorded_rsu_message_is_replayed_and_answered(runs):
    _, replayed, recording = runs
    stats = replayed["replay"]
    recorded = sum(1 for _ in recording.samples("vehicle", "v2x/rsu/**"))
    assert stats["published"] == recorded > 0
    assert stats.get("unshifted", 0) == 0
    assert stats["envelopes_removed"] == sum(1 for s in recording.samples("vehicle", "v2x/rsu/**") if s.signed) > 0
    assert stats["recorded_security"] == "strict" and replayed["security"] is None
    assert stats["time_replies"] > 0


def test_the_replayed_obu_scores_like_the_live_one(runs):
    live, replayed, _ = runs
    assert set(replayed) - set(live) == {"replay", "recording"} and set(live) <= set(replayed)
    assert replayed["driver"] == "replay" and replayed["outputs"] == live["outputs"] == 80
    assert replayed["rsu_messages_received"] == pytest.approx(live["rsu_messages_received"], rel=0.05)
    t_live, t_replay = live["target"], replayed["target"]
    assert t_live["first_detection_distance_m"] is not None
    assert t_replay["first_detection_distance_m"] == pytest.approx(t_live["first_detection_distance_m"], rel=0.05)
    assert t_replay["detected_cycles"] == pytest.approx(t_live["detected_cycles"], rel=0.1)
    assert t_replay["mean_bev_iou"] == pytest.approx(t_live["mean_bev_iou"], rel=0.1)
