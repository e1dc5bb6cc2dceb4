"""The offline runner: deterministic per seed, and V2I sees the runner far earlier."""

import json

import pytest

from evaluation.runner import OfflineRun
from evaluation.spec import RunSpec, build_report
from v2i.cli import main

REQUIRED = {"scenario", "profile", "fusion", "seed", "duration_s", "cycles", "output_deadline_miss_ratio",
            "target", "vehicle_only", "clock_offset_error_ms"}


def report(seed: int, **kw) -> dict:
    run = OfflineRun(RunSpec(seed=seed, duration_s=12.0, **kw))
    return build_report(run.spec, run.world, run.execute(), driver="eval")


def test_same_seed_same_report_other_seed_differs():
    a, b, c = report(1), report(1), report(2)
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    assert a["target"] != c["target"]
    assert REQUIRED <= set(a)
    assert {"mean_bev_iou", "rmse_m", "first_detection_distance_m"} <= set(a["target"])
    assert {"p50", "p95", "max"} <= set(a["clock_offset_error_ms"])


def test_v2i_first_detection_at_least_three_times_vehicle_only():
    r = report(0)
    assert r["target"]["first_detection_distance_m"] >= 3 * r["vehicle_only"]["first_detection_distance_m"]
    assert r["output_deadline_miss_ratio"] == 0.0


def test_clock_offset_is_recovered_offline():
    r = report(0, rsu_clock_offset_ms=350.0, rsu_clock_drift_ppm=20.0)
    assert r["clock_offset_error_ms"]["p95"] < 10.0


def test_vehicle_only_fusion_never_uses_rsu():
    r = report(0, fusion="vehicle-only")
    assert r["target"]["first_detection_distance_m"] == r["vehicle_only"]["first_detection_distance_m"]


def test_cli_rejects_unknown_scenario_and_profile(capsys):
    assert main(["eval", "--scenario", "no-such-place"]) == 2
    assert "red-light-runner" in capsys.readouterr().err
    assert main(["eval", "--profile", "carrier-pigeon"]) == 2
    assert "lte-v2x" in capsys.readouterr().err


def test_cli_eval_json_stdout(capsys):
    assert main(["eval", "--duration", "3", "--json", "-"]) == 0
    out = capsys.readouterr()
    assert REQUIRED <= set(json.loads(out.out))
    assert "red-light-runner" in out.err


@pytest.mark.parametrize("cmd", ["demo", "eval", "rsu", "obu", "link"])
def test_every_subcommand_explains_itself(cmd, capsys):
    with pytest.raises(SystemExit) as exc:
        main([cmd, "--help"])
    assert exc.value.code == 0
    assert len(capsys.readouterr().out) > 200
