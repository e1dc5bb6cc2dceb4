"""Accounting of ``v2i attack`` (v2i.adversary.attack_report): counter growth per phase, labels split by
what the verifier did, and the verdict."""

from __future__ import annotations

from v2i.adversary.attack_report import counter_delta, format_report, got_through, kind_row, split_labels


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
