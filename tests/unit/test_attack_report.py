"""Accounting of ``v2i attack`` (v2i.adversary.attack_report): counter growth per phase, labels split by
what the verifier did, and the verdict."""

from __future__ import annotations

import pytest

from schemas.messages import RsuLinkStatus
from v2i.adversary.attack_report import (counter_delta, flood_row, format_report, genuine_sent_in, got_through, kind_row,
                                         relay_row, split_labels)


def test_counter_delta_keeps_only_what_grew():
    assert counter_delta({"a": 5, "b": 2, "c": 1}, {"a": 3, "b": 2}) == {"a": 2, "c": 1}


def test_labels_split_into_dropped_accepted_and_other():
    dropped, accepted, other = split_labels({"security_unsigned": 3, "security_accepted_revoked": 2, "duplicate": 1})
    assert (dropped, accepted, other) == ({"unsigned": 3}, {"revoked": 2}, {"duplicate": 1})


def _report(**rows) -> dict:
    genuine = {"window_s": 10.0, "rsu_lists_sniffed": 50, "rsu_lists_accepted": 49, "outputs": 100,
               "outputs_with_rsu_objects": 99, "output_deadline_misses": 0, "cycles": 100}
    baseline = {"window_s": 3.0, "rsu_lists_sniffed": 15, "rsu_lists_accepted": 15, "outputs": 30,
                "false_positive_outputs": 0, "rejected": {}}
    return {"rsu_id": "rsu1", "vehicle_id": "ego", "count": 10, "rate_hz": 30.0, "kinds": rows, "genuine": genuine,
            "baseline": baseline}


def test_all_rejected_is_nothing_through_and_each_leak_is_named():
    stopped = kind_row("forged", {"forged": 10}, {"security_bad_signature": 10}, 0, 0, 30, 1.0)
    assert stopped["rejected_as_intended"] == 10 and got_through(_report(forged=stopped)) == []
    leaked = kind_row("unsigned", {"unsigned": 10}, {"security_accepted_unsigned": 10}, 7, 7, 30, 1.0)
    control = kind_row("control", {"unsigned": 5, "wrong_key": 5}, {}, 0, 0, 30, 1.0,
                       control_delta={"unsigned": 5, "wrong_role": 4}, control_applied=1)
    notes = got_through(_report(unsigned=leaked, control=control))
    assert any("unsigned: 10 of 10 failed verification and were accepted" in n for n in notes)
    assert any("ghost in 7" in n for n in notes) and any("1 applied" in n for n in notes)
    assert any("control: 1 of 10 not rejected" in n for n in notes)
    text = format_report(_report(unsigned=leaked, control=control))
    assert "ghost in 7 of 30 outputs" in text and "applied by the emulator: 1" in text


def test_a_moved_clock_and_output_misses_are_reported():
    time_row = kind_row("time", {"unsigned": 3}, {"security_unsigned": 3}, 0, 0, 30, 1.0, clock_shift_ms=399.5)
    report = _report(time=time_row)
    report["genuine"]["output_deadline_misses"] = 2
    notes = got_through(report)
    assert any("moved 399.5 ms" in n for n in notes) and any("2 output deadline misses" in n for n in notes)


def test_genuine_lists_count_in_the_metrics_window_shifted_by_the_delay():
    sniffed = [1_000, 1_200, 1_400, 1_600, 1_800]  # lists at the RSU; each reaches the OBU 50 later
    assert genuine_sent_in(sniffed, 1_100, 1_700, 0) == 3  # (1100, 1700]: 1200, 1400, 1600
    assert genuine_sent_in(sniffed, 1_100, 1_700, 50) == 3  # (1050, 1650]: the same three
    assert genuine_sent_in(sniffed, 1_020, 1_630, 50) == 3  # (970, 1580]: 1000 arrives at 1050 > 1020
    assert genuine_sent_in(sniffed, 1_000, 1_000, 0) == 0


def _flood(accepted: int, sent: int = 100, **extra) -> dict:
    row = flood_row({"junk": 667, "unsigned": 667, "forged": 666}, 100.0, 20.0, sent, accepted,
                    {"security_unsigned": 1000, "security_bad_signature": 666, "security_malformed": 334},
                    {"intra": 150, "inter": 40, "planning": 10}, 0, 200, 0, 200, 20.3)
    row.update(extra)
    return row


def test_a_flood_that_starves_the_genuine_rsu_is_named_and_one_that_does_not_is_not():
    fine, starved = _flood(96), _flood(20)
    assert fine["rejected_as_intended"] == fine["rejected_total"] == 2000 and fine["achieved_hz"] == 100.0
    assert got_through(_report(flood=fine)) == []
    notes = got_through(_report(flood=starved))
    assert notes == ["flood: the OBU accepted 20 of the genuine RSU's 100 lists (at 100 msg/s)"]
    assert any("a ghost in 3" in n for n in got_through(_report(flood=_flood(99, ghost_outputs=3))))
    text = format_report(_report(flood=starved))
    assert "genuine accepted 20 of 100" in text and "modes intra 150, inter 40, planning 10" in text


def _relay(first_sync_s, steps_after: int = 0) -> dict:
    before, after = RsuLinkStatus(rsu_id="rsu1", sync_samples=10), RsuLinkStatus(
        rsu_id="rsu1", sync_samples=310, clock_steps=steps_after)
    samples = [(1_000, 350_400_000, 4_000_000), (2_000, 350_900_000, 3_000_000)]
    return relay_row({"queries": 300, "forwarded": 300, "rsu_replies": 5, "returned": 5, "unanswered": 295},
                     before, after, first_sync_s, 350_000_000, samples, {"security_replayed": 5},
                     {"intra": 200, "inter": 80, "vehicle-only": 20}, 0, 300, 30.0, delay_ms=100.0)


def test_a_relay_row_gives_the_clock_and_names_a_late_sync_or_a_step():
    row = _relay(0.1)
    assert (row["sync_samples"], row["clock_steps"], row["offset_error_ms"]) == (300, 0, 0.9)
    assert row["tracking_share"] == pytest.approx(280 / 300) and row["uncertainty_ms"] == 3.0
    assert got_through(_report(time_delayed=row)) == []
    notes = got_through(_report(time_doubled=_relay(None), time_delayed=_relay(4.5, steps_after=1)))
    assert notes == ["time_doubled: the OBU never synchronised its clock to the RSU",
                     "time_delayed: the OBU's clock synchronised only 4.5 s after its start",
                     "time_delayed: 1 RSU clock steps confirmed (none happened)"]
    text = format_report(_report(time_delayed=row))
    assert "relayed 300 of 300 queries (delay 100 ms), RSU answered 5" in text and "intra/inter 93 %" in text
    assert relay_row({}, None, None, None, None, [], {}, {}, 0, 0, 0.0)["tracking_share"] is None
