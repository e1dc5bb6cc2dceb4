"""Which run a recording is of (``v2i.offline.recorded_run.run_of``): a ``v2i demo --record`` file
says it, a ``v2i record`` file needs the scenario and start from the command line; and how
``v2i replay`` says what it did (readable lines, not a dict)."""

from __future__ import annotations

import pytest

from v2i.offline.recorded_run import RUN_METADATA, run_metadata, run_of
from v2i.offline.spec import RunSpec
from schemas.codec import encode
from schemas.messages import ObjectList, ObjectListHeader
from v2i.telemetry.mcap_reader import Recording
from v2i.telemetry.mcap_writer import RunWriter
from v2i.replay import replay_summary

T_NS = 1_795_545_547_592_119_513
S = 1_000_000_000


def _list(seq: int) -> bytes:
    header = ObjectListHeader(rsu_id="rsu1", seq=seq, capture_time_ns=T_NS, publish_time_ns=T_NS)
    return encode(ObjectList(header=header, objects=[]))


def _recording(path, metadata: dict | None = None, cpm: bool = False) -> Recording:
    """RSU lists logged 0.5 s to 7.25 s after T_NS on the vehicle side (what v2i record writes)."""
    writer = RunWriter(path)
    writer.add_metadata("recording", {"started_ns": str(T_NS)})
    for name, data in (metadata or {}).items():
        writer.add_metadata(name, data)
    for i, t_ns in enumerate((T_NS + S // 2, T_NS + 3 * S, T_NS + 7 * S + S // 4)):
        writer.write("vehicle", "v2x/rsu/rsu1/objects", _list(i), t_ns)
    if cpm:
        writer.write("vehicle", "v2x/rsu/rsu1/cpm", b"\x01\x02", T_NS + S)
    writer.close()
    return Recording(path)


def test_a_v2i_record_file_needs_its_scenario_and_start(tmp_path):
    recording = _recording(tmp_path / "r.mcap")
    with pytest.raises(ValueError, match=r"r\.mcap has no run metadata .* give --scenario and --start-at-ns,"):
        run_of(recording, {"scenario": None, "start_ns": None, "seed": None})
    with pytest.raises(ValueError, match=r"give --start-at-ns,"):
        run_of(recording, {"scenario": "red-light-runner"})
    with pytest.raises(ValueError, match=r"give --scenario,"):
        run_of(recording, {"start_ns": T_NS})
    spec, start_ns = run_of(recording, {"scenario": "highway-merge", "start_ns": T_NS, "seed": None})
    assert start_ns == T_NS and spec.scenario == "highway-merge" and spec.seed == RunSpec().seed
    assert spec.profile == "recorded" and spec.wire == "v2i" and spec.security is None
    assert spec.duration_s == 7.3  # the last RSU sample 7.25 s after the start, rounded up to 0.1 s
    spec, _ = run_of(recording, {"scenario": "highway-merge", "start_ns": T_NS + S, "seed": 4, "duration_s": 2.5})
    assert spec.seed == 4 and spec.duration_s == 2.5
    with pytest.raises(ValueError, match="none after --start-at-ns"):
        run_of(recording, {"scenario": "highway-merge", "start_ns": T_NS + 8 * S})
    spec, _ = run_of(_recording(tmp_path / "cpm.mcap", cpm=True), {"scenario": "highway-merge", "start_ns": T_NS})
    assert spec.wire == "cpm"  # the OBU must subscribe to what was recorded


def test_a_demo_recording_says_its_run_and_the_command_line_wins(tmp_path):
    recorded = RunSpec(scenario="highway-merge", profile="dsrc", seed=3, duration_s=None, security="strict")
    meta = {RUN_METADATA: run_metadata(recorded, T_NS, 6.0, "ego", "rsu1")}
    recording = _recording(tmp_path / "demo.mcap", meta)
    spec, start_ns = run_of(recording, {"scenario": None, "seed": None})
    assert (spec.scenario, spec.profile, spec.seed, spec.duration_s, spec.security) == (
        "highway-merge", "dsrc", 3, 6.0, "strict")
    assert start_ns == T_NS
    spec, start_ns = run_of(recording, {"seed": 9, "start_ns": T_NS + S})
    assert spec.seed == 9 and start_ns == T_NS + S and spec.scenario == "highway-merge"


def test_the_replay_says_what_it_did_in_words():
    stats = {"side": "vehicle", "keys": "v2x/rsu/**", "speed": 1.0, "shift_ns": 12_345_000_000, "published": 812,
             "late": 3, "time_replies": 120, "envelopes_removed": 812,
             "lateness_ms": {"p50": 0.41, "p95": 2.0, "p99": 4.04, "max": 7.2},
             "rsu_clocks": {"rsu1": {"exchanges_used": 98, "exchanges_dropped": 2}}, "recorded_security": "strict"}
    text = replay_summary(stats)
    assert "{" not in text and "'" not in text  # no Python dict
    assert text.splitlines() == [
        "v2i replay: published 812 samples of side vehicle (v2x/rsu/**) at speed 1, every stamp moved by 12.345 s; "
        "late by p50 0.4 ms, p99 4.0 ms, max 7.2 ms, 3 later than 5 ms",
        "  RSU clocks: rsu1 from 98 recorded exchanges (2 left out); 120 time queries answered",
        "  812 signed samples republished unsigned; the recorded run signed (strict), the fresh OBU does not"]
    nothing = {"side": "rsu", "keys": "v2x/rsu/**", "speed": 2.0, "shift_ns": 0,
               "lateness_ms": {"max": None}, "rsu_clocks": {}}
    assert replay_summary(nothing).splitlines() == [
        "v2i replay: published 0 samples of side rsu (v2x/rsu/**) at speed 2, every stamp moved by 0.000 s",
        "  RSU clocks: none recorded; 0 time queries answered"]
