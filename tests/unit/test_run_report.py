"""``--report DIR``: the run report's pictures and the per-cycle series behind them."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from v2i.offline.chaos import ChaosTimeline, load_chaos, with_chaos
from v2i.scoring.link_series import LinkSeries
from v2i.scoring.metrics import deadline_miss_ratio
from v2i.reports.run_arrays import chaos_spans, missed_cycles_ns, rsu_traces, vehicle_timeline
from v2i.reports.run_report import write_offline_report
from v2i.offline.runner import OfflineRun
from v2i.offline.spec import RunSpec
from schemas.messages import RsuLinkStatus
from v2i.cli import main

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def png_size(path) -> tuple[int, int]:
    """(width, height) px from the PNG's IHDR chunk."""
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


@pytest.fixture(scope="module")
def offline():
    run = OfflineRun(RunSpec(scenario="red-light-runner", seed=1, duration_s=12.0), link_series=True)
    run.execute()
    return run, run.report()


def test_offline_report_writes_the_pngs_and_the_report(offline, tmp_path):
    run, report = offline
    written = write_offline_report(tmp_path / "new" / "dir", report, run)
    assert [p.name for p in written] == ["timeline.png", "bev.png", "report.json"]
    for path in written[:2]:
        width, height = png_size(path)
        assert 800 <= width <= 3000 and 500 <= height <= 3000, (path.name, width, height)
    assert json.loads(written[2].read_text()) == report


def test_link_series_is_one_sample_per_cycle_and_rsu(offline):
    run, report = offline
    record = run.record
    (trace,) = rsu_traces(run.spec, record)
    # one sample per cycle once the OBU knows the RSU (from its first list on), at the publish time
    publish_s = (np.array(record.cycles.publish_ns) - record.start_ns) * 1e-9
    assert report["outputs"] - 2 <= len(trace.t_s) == len(np.unique(trace.t_s)) <= report["outputs"]
    assert np.isin(trace.t_s, publish_s).all()
    assert trace.rsu_id == "rsu-nw"
    settled = trace.t_s >= 5.0  # the report scores clock errors after a 5 s warm-up
    # the same errors as the report's (the estimate at each cycle): |error| p95 within 1e-6 ms
    p95 = np.percentile(np.abs(trace.offset_error_ms[settled]), 95)
    assert p95 == pytest.approx(report["clock_offset_error_ms"]["p95"], abs=1e-4)
    assert np.nanmax(trace.delay_p50_ms) > 0 and np.all(np.isfinite(trace.age_ms[settled]))


def test_timeline_series_agree_with_the_report(offline):
    run, report = offline
    tl = vehicle_timeline(run.spec, "ego", run.record)
    assert len(tl.cycle_s) == len(tl.modes) == report["outputs"]
    assert np.all(np.diff(tl.cycle_s) > 0)
    rmse = np.sqrt(np.mean(np.square(tl.target.error_m)))
    assert rmse == pytest.approx(report["target"]["rmse_m"], abs=1e-4)
    assert len(tl.vehicle_only.t_s) == report["vehicle_only"]["detected_cycles"]
    assert set(np.unique(tl.vehicle_only.sources)) <= {1, 3}  # every vehicle-only match has the own bit
    assert 2 in tl.target.sources  # the runner is seen by the RSU alone before the LiDAR sees it


@pytest.mark.parametrize("deadline_ms", [45.0, 60.0, 100.0])
def test_missed_cycles_are_the_ratios_misses(offline, deadline_ms):
    record = offline[0].record
    missed = missed_cycles_ns(record, deadline_ms)
    ratio = deadline_miss_ratio(record.cycle_times_ns, record.cycles.cycle_ns, record.cycles.publish_ns, deadline_ms)
    assert len(missed) / len(record.cycle_times_ns) == ratio
    assert np.isin(missed, record.cycle_times_ns).all()
    if deadline_ms == 45.0:  # most cycles publish ~50 ms after capture
        assert len(missed) > len(record.cycle_times_ns) / 2


def test_link_series_keeps_unknowns_as_nan_per_rsu():
    series = LinkSeries()
    series.add(10, [RsuLinkStatus(rsu_id="a"), RsuLinkStatus(rsu_id="b", clock_offset_ns=5_000_000,
                                                               clock_uncertainty_ns=1_000, delay_p50_ms=20.0,
                                                               messages_accepted=3)])
    series.add(20, [RsuLinkStatus(rsu_id="b", last_data_age_ms=150.0, messages_accepted=4)])
    a, b = series.per_rsu()
    assert (a.rsu_id, b.rsu_id) == ("a", "b")
    assert list(a.t_ns) == [10] and np.isnan(a.offset_ns[0]) and np.isnan(a.delay_p50_ms[0])
    assert list(b.t_ns) == [10, 20] and list(b.accepted) == [3, 4]
    assert b.offset_ns[0] == 5_000_000 and b.uncertainty_ns[0] == 1_000 and b.delay_p50_ms[0] == 20.0
    assert np.isnan(b.age_ms[0]) and b.age_ms[1] == 150.0


TIMELINE = ChaosTimeline.model_validate({"name": "t", "events": [
    {"at_s": 16.0, "kill": "link"}, {"at_s": 2.0, "delay_spike": {"duration_s": 2.0, "extra_ms": 300,
                                                                   "direction": "downlink"}},
    {"at_s": 19.0, "restart": "link"}, {"at_s": 10.0, "profile": "dsrc"}, {"at_s": 25.0, "kill": "rsu"},
    {"at_s": 28.0, "outage": {"duration_s": 10.0}}]})


def test_chaos_spans_offline_at_the_scheduled_times():
    spans = chaos_spans(TIMELINE, end_s=30.0)
    assert [(s.from_s, s.to_s, s.kind) for s in spans] == [
        (2.0, 4.0, "delay_spike"), (10.0, 10.0, "profile"), (16.0, 19.0, "kill"), (19.0, 19.0, "restart"),
        (25.0, 30.0, "kill"), (28.0, 30.0, "outage")]  # never restarted / past the end: cut at the end
    assert [s.instant for s in spans] == [False, True, False, True, False, False]
    assert spans[0].short == "+300 ms delay (down)" and spans[2].short == "link killed"
    assert spans[0].label == "delay_spike +300 ms on downlink for 2 s"


def test_chaos_spans_live_from_the_fired_times():
    events = {e.at_s: e for e in TIMELINE.events}
    fired = [(2.04, events[2.0]), (16.02, events[16.0]), (19.5, events[19.0])]  # played late; some not at all
    spans = chaos_spans(TIMELINE, end_s=30.0, fired=fired)
    assert [(s.from_s, s.to_s) for s in spans] == [(2.04, 4.04), (16.02, 19.5), (19.5, 19.5)]


def test_eval_report_flag_writes_the_run_pictures(tmp_path, capsys):
    folder = tmp_path / "out"
    assert main(["eval", "--duration", "3", "--report", str(folder), "--json", str(tmp_path / "r.json")]) == 0
    assert sorted(p.name for p in folder.iterdir()) == ["bev.png", "report.json", "timeline.png"]
    assert json.loads((folder / "report.json").read_text()) == json.loads((tmp_path / "r.json").read_text())


def test_eval_report_into_a_file_fails_before_the_run(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["eval", "--report", str(blocker / "sub")]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err


def test_site_eval_writes_a_timeline_per_vehicle(tmp_path):
    chaos = load_chaos("examples/chaos/outage-10s.yaml")
    spec = with_chaos(RunSpec(scenario="connected-intersection", seed=1, duration_s=6.0), chaos)
    run = OfflineRun(spec, chaos=chaos, link_series=True)
    run.execute()
    names = [p.name for p in write_offline_report(tmp_path, run.report(), run)]
    assert names == ["timeline-ego.png", "timeline-car-2.png", "timeline-car-3.png", "bev.png", "report.json"]
    assert {s.rsu_id for s in run.records["car-3"].links.per_rsu()} == {"rsu-nw", "rsu-se"}
