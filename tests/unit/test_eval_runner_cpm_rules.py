"""v2i eval --wire cpm --cpm-rules: the RSU sends by TS 103 324's generation rules (rsu_service.cpm_rules),
segmented to the MTU; without the flag nothing changes."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from rsu_service.config import RsuConfig
from rsu_service.cpm_segments import segment_info
from schemas import list_wire
from v2i import cli
from v2i.offline.runner import OfflineRun
from v2i.offline.spec import RunSpec


def _run(rules: bool, **kw) -> OfflineRun:
    run = OfflineRun(RunSpec(scenario="dense-intersection", wire="cpm", seed=0, duration_s=4.0, cpm_rules=rules, **kw))
    run.execute()
    return run


@pytest.fixture(scope="module")
def ruled() -> tuple[OfflineRun, list[bytes]]:
    """A 4 s dense-intersection run under the rules, and every object list its RSU sent."""
    sent: list[bytes] = []
    real = OfflineRun._broadcast

    def broadcast(self, rsu, data, deliver):  # the object lists (not the predictions), as sent
        if deliver.__name__ == "_obu_receive":
            sent.append(data)
        real(self, rsu, data, deliver)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(OfflineRun, "_broadcast", broadcast)
        return _run(True), sent


def test_rules_send_fewer_bytes_in_segments_within_the_mtu(ruled):
    run, sent = ruled
    report = run.report()
    lists = report["rsu_lists"]
    assert report["cpm_rules"] is True and lists["bytes"] == sum(map(len, sent))
    assert lists["bytes"] < 0.7 * _run(False).rsu_lists_sent()["bytes"]  # dense-intersection: ~49 % less
    assert lists["segmented"] > 0 and max(map(len, sent)) <= 1100
    infos = [segment_info(d) for d in sent]
    assert any(info is not None and info[1] > 1 for info in infos)
    assert set(lists["included_by"]) <= {"new", "position", "speed", "heading", "refresh", "vru_refresh"}
    origin = run.site_config.origin.lat_deg, run.site_config.origin.lon_deg
    objects = sum(len(list_wire.decode_list(d, "cpm", "rsu1", origin=origin).objects) for d in sent)
    assert objects == lists["objects"]  # every object the rules included went out, once


def test_the_obu_reads_every_segment_on_its_own(ruled):
    run, sent = ruled  # schemas.cpm.sequence: 8 referenceTime + thisMsgNo - 1, so no segment is a duplicate
    report = run.report()
    assert report["obu_rejected"].get("duplicate", 0) == 0, report["obu_rejected"]
    assert report["rsu_messages_received"] > 0.8 * len(sent)


def test_without_the_flag_the_report_is_unchanged():
    report = OfflineRun(RunSpec(seed=0, duration_s=1.0)).report()
    assert "cpm_rules" not in report and "rsu_lists" not in report


def test_rules_need_the_cpm_wire(capsys):
    with pytest.raises(ValidationError, match="wire cpm"):
        RunSpec(cpm_rules=True).rsu_config()
    with pytest.raises(ValidationError, match="wire cpm"):
        RsuConfig(scenario="red-light-runner", wire="sdsm", cpm_rules=True)
    assert cli.main(["eval", "--cpm-rules", "--duration", "1"]) != 0
    assert "--cpm-rules" in capsys.readouterr().err
