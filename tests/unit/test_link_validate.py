"""``v2i link validate``: declared against achieved channel statistics (pure, plus the CLI)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from link_emulator import cli as link_cli
from link_emulator.channel import NS_PER_MS, LinkModel
from link_emulator.profile import DirectionProfile, bundled_profiles, load_profile
from link_emulator.trace import load_trace
from link_emulator.validate import (
    P50_Z,
    T0_NS,
    Settings,
    achieved,
    declared,
    declared_law,
    p50_range_ms,
    quantile_ms,
    summarise,
    validate_direction,
)
from v2i.cli import build_parser, main

TRACE = "cicv5g/urban_n78_v20_run01.txt.gz"
# 1e6 messages: a 0.8 % loss ratio has a relative standard error of 1.1 %, so 10 % is 9 sigma;
# the p50 range is 4 standard errors at the delivered count (see validate.p50_range_ms).
SAMPLES = 1_000_000
HEADER = "pub_time(ms) sub_time(ms) delay(ms)"


def _direction(**fields) -> DirectionProfile:
    return DirectionProfile.model_validate(fields)


@pytest.mark.parametrize("name", bundled_profiles())
def test_every_shipped_profile_validates_within_tolerance(name: str) -> None:
    direction = load_profile(name).downlink
    outage = direction.outage
    if outage is not None and outage.mode == "hold" and outage.random_down_fraction() > 0.01:
        # outage hold is emergent, not declared (see validate's module doc); rural-5g-buffered holds
        # for 2-30 s on purpose: validate the rest of it
        direction = direction.model_copy(update={"outage": None})
    report = validate_direction(name, "downlink", direction, Settings(samples=SAMPLES))
    assert report["pass"], report
    declared_s, achieved_s = report["declared"], report["achieved"]
    assert abs(achieved_s["loss_ratio"] - declared_s["loss_ratio"]) <= 0.1 * declared_s["loss_ratio"] + 1e-12
    low, high = report["p50_range_ms"]
    assert low <= declared_s["p50_ms"] <= high and low <= achieved_s["p50_ms"] <= high


@pytest.mark.parametrize("name", ["lte-v2x", "cellular-uu", "iaad-field", "congested"])
def test_uplinks_validate_too(name: str) -> None:
    report = validate_direction(name, "uplink", load_profile(name).uplink, Settings(samples=200_000))
    assert report["pass"], report


def test_trace_replay_reproduces_the_trace() -> None:
    trace = load_trace(TRACE)
    report = validate_direction("5g-uu-trace", "downlink", load_profile("5g-uu-trace").downlink,
                                Settings(samples=200_000))
    assert report["achieved"]["p50_ms"] == np.median(trace.delay_ms)
    assert abs(report["achieved"]["p99_ms"] - np.percentile(trace.delay_ms, 99)) <= 1.0
    assert report["ks_statistic"] < 0.01
    assert report["declared_method"]["delay"] == "trace"
    assert report["overtaken_ratio"] == 0.0 and report["checks"]["replay_keeps_order"]
    assert report["effective_samples"] == trace.delay_ms.size  # a replay knows no more than its rows
    # in step with the trace's median period, the replay meets its gaps (the trace's irregular
    # send times join some of them); the declaration draws the same gap windows independently
    per_slot = validate_direction("t", "downlink", load_profile("5g-uu-trace").downlink,
                                  Settings(samples=50_000, interval_ms=trace.period_ms))
    assert per_slot["declared_method"]["mean_burst_len"] == "monte-carlo"
    assert per_slot["achieved"]["mean_burst_len"] == pytest.approx(per_slot["declared"]["mean_burst_len"], rel=0.05)
    assert trace.mean_burst_len <= per_slot["achieved"]["mean_burst_len"] < 1.5 * trace.mean_burst_len


def test_an_exact_replay_passes_because_both_sides_use_one_quantile_definition(tmp_path: Path) -> None:
    # 148 rows of 10 ms and a plateau of two at 30 ms (arrivals monotonic), irregular send times
    delays = [30 if k in (70, 71) else 10 for k in range(150)]
    pubs = np.cumsum([0] + [46 + (7 * k) % 9 for k in range(149)])
    path = tmp_path / "plateau.txt"
    path.write_text("\n".join([HEADER] + [f"{p} {p + d} {d}" for p, d in zip(pubs, delays)]))
    direction = _direction(delay_ms=0.0, replay={"trace": str(path)})
    report = validate_direction("plateau", "downlink", direction, Settings(samples=200_000))
    # numpy's default (linear) p99 of the trace lies between 10 and 30, where no replay lands:
    # that was the declared p99, and the exact replay failed the 3 ms check
    assert np.quantile(delays, 0.99) == pytest.approx(20.2)
    assert abs(report["achieved"]["p99_ms"] - np.quantile(delays, 0.99)) > 3.0
    assert report["declared"]["p99_ms"] == report["achieved"]["p99_ms"] == 30.0
    assert report["declared"]["p50_ms"] == report["achieved"]["p50_ms"] == 10.0
    assert report["pass"], report


def test_p50_range_is_the_sampling_error_of_a_median() -> None:
    # a smooth law: Z sd of the sample median, sd = sqrt(p (1 - p) / n) / f(Q(p)), f(Q(.5)) = 1 / (sqrt(2 pi) s)
    normal = _direction(delay_ms=100.0, jitter={"distribution": "normal", "std_ms": 10.0})
    low, high = p50_range_ms(declared_law(normal, Settings()), 10_000)
    half_ms = P50_Z * math.sqrt(0.25 / 10_000) * math.sqrt(2.0 * math.pi) * 10.0
    assert (high - 100.0) == pytest.approx(half_ms, rel=0.01) and (100.0 - low) == pytest.approx(half_ms, rel=0.01)
    # a heavy tail at few samples is wide, a light one at many samples narrow
    otvic = validate_direction("otvic-field", "downlink", load_profile("otvic-field").downlink, Settings(samples=10_000))
    assert otvic["p50_range_ms"][1] - otvic["p50_range_ms"][0] > 10.0 and otvic["checks"]["p50_within_sampling_error"]
    dsrc = validate_direction("dsrc", "downlink", load_profile("dsrc").downlink, Settings(samples=100_000))
    assert dsrc["p50_range_ms"][1] - dsrc["p50_range_ms"][0] < 0.1
    # correlation leaves fewer independent draws: n (1 - rho) / (1 + rho)
    assert validate_direction("c", "downlink", _direction(delay_ms=1.0, jitter={"distribution": "normal", "std_ms": 1.0},
                                                          correlation=0.5), Settings(samples=3000))["effective_samples"] == 1000


@pytest.mark.parametrize("samples", [1_000, 100_000])
def test_p50_check_passes_the_declared_law_and_fails_a_clearly_wrong_one(samples: int) -> None:
    direction = _direction(delay_ms=5.0, jitter={"distribution": "pareto", "scale_ms": 10.0, "shape": 1.5})
    law = declared_law(direction, Settings())
    low, high = p50_range_ms(law, samples)
    rng = np.random.default_rng(7)
    right = [quantile_ms(5.0 + 10.0 * rng.pareto(1.5, samples), 0.5) for _ in range(50)]
    assert all(low <= m <= high for m in right)
    wrong = [quantile_ms(5.0 + 10.0 * rng.pareto(1.5, samples) * 1.5, 0.5) for _ in range(50)]  # scale 15 ms
    assert not any(low <= m <= high for m in wrong)


def test_ks_statistic_detects_a_profile_that_does_not_match_its_trace() -> None:
    shifted = _direction(delay_ms=5.0, replay={"trace": TRACE})  # 5 ms more than the trace
    report = validate_direction("shifted", "downlink", shifted, Settings(samples=20_000))
    assert report["ks_statistic"] < 0.02  # the reference includes delay_ms
    empirical = _direction(delay_ms=0.0, jitter={"distribution": "empirical", "trace": TRACE}, correlation=0.5)
    good = validate_direction("emp", "downlink", empirical, Settings(samples=50_000))
    assert good["ks_statistic"] < 0.02
    wrong = _direction(delay_ms=0.0, jitter={"distribution": "normal", "mean_ms": 16.0, "std_ms": 3.0})
    delays = validate_direction("w", "downlink", wrong, Settings(samples=10))
    assert "ks_statistic" not in delays  # not a trace profile


def test_declared_values_are_analytic_where_possible() -> None:
    direction = _direction(delay_ms=2.0, jitter={"distribution": "exponential", "scale_ms": 4.0},
                           loss_probability=0.2, mean_burst_len=4.0, bandwidth_kbps=800.0)
    summary, methods = declared(direction, Settings(size_bytes=1000))  # serialization 10 ms
    assert methods == {"delay": "analytic", "loss_ratio": "analytic", "mean_burst_len": "analytic"}
    assert summary.p50_ms == pytest.approx(12.0 + 4.0 * math.log(2.0))
    assert summary.p99_ms == pytest.approx(12.0 + 4.0 * math.log(100.0))
    assert summary.mean_ms == pytest.approx(16.0)
    assert summary.loss_ratio == pytest.approx(0.2) and summary.mean_burst_len == pytest.approx(4.0)
    bernoulli, _ = declared(_direction(delay_ms=1.0, loss_probability=0.2), Settings())
    assert bernoulli.mean_burst_len == pytest.approx(1.25)


def test_declared_loss_combines_independent_mechanisms() -> None:
    direction = _direction(delay_ms=1.0, loss_probability=0.1, pdr_curve=[[0, 1.0], [100, 0.5]],
                           outage={"mean_interval_s": 9.0, "duration_s": [1.0, 1.0]})
    summary, methods = declared(direction, Settings(distance_m=100.0))
    assert summary.loss_ratio == pytest.approx(1.0 - 0.9 * 0.5 * 0.9)
    assert methods["mean_burst_len"] == "monte-carlo"
    report = validate_direction("combo", "downlink", direction, Settings(samples=300_000, distance_m=100.0))
    assert report["pass"]
    assert report["achieved"]["mean_burst_len"] == pytest.approx(summary.mean_burst_len, rel=0.05)


def test_declared_delay_uses_monte_carlo_with_spikes() -> None:
    direction = _direction(delay_ms=10.0, spikes={"probability": 0.5, "extra": {"distribution": "uniform",
                                                                              "low_ms": 100.0, "high_ms": 100.0}})
    summary, methods = declared(direction, Settings())
    assert methods["delay"] == "monte-carlo"
    assert summary.mean_ms == pytest.approx(60.0, abs=0.2)
    assert summary.p99_ms == pytest.approx(110.0)


def test_scheduled_outage_windows_count_within_the_validation_span() -> None:
    direction = _direction(delay_ms=1.0, outage={"windows_s": [[10.0, 20.0], [15.0, 30.0]]})
    summary, _ = declared(direction, Settings(samples=1000, interval_ms=100.0))  # 100 s span
    assert summary.loss_ratio == pytest.approx(0.2)
    report = validate_direction("w", "downlink", direction, Settings(samples=1000))
    assert report["achieved"]["loss_ratio"] == pytest.approx(0.2)
    assert report["achieved"]["mean_burst_len"] == pytest.approx(200.0)


def test_summarise() -> None:
    s = summarise(np.arange(1.0, 101.0), np.array([True, True, False, True, False]))
    assert s.mean_ms == pytest.approx(50.5) and s.p50_ms == 50.0  # min{x : F_n(x) >= 0.5}, as declared ones
    assert s.loss_ratio == pytest.approx(0.6) and s.mean_burst_len == pytest.approx(1.5)
    empty = summarise(np.array([]), np.array([True, True]))
    assert empty.p50_ms is None and empty.loss_ratio == 1.0


def test_pareto_with_infinite_mean_reports_none() -> None:
    direction = _direction(delay_ms=1.0, jitter={"distribution": "pareto", "scale_ms": 1.0, "shape": 0.9})
    report = validate_direction("p", "downlink", direction, Settings(samples=1000))
    assert report["declared"]["mean_ms"] is None
    json.dumps(report)  # strict JSON: no Infinity


# ---- the command line ------------------------------------------------------------------------


def test_cli_json_report(capsys) -> None:
    code = main(["link", "validate", "--profile", "dsrc", "--samples", "20000", "--json", "-"])
    report = json.loads(capsys.readouterr().out)
    assert code == 0
    assert {"profile", "samples", "declared", "achieved"} <= set(report)
    keys = {"mean_ms", "p50_ms", "p95_ms", "p99_ms", "loss_ratio", "mean_burst_len"}
    assert set(report["declared"]) == keys and set(report["achieved"]) == keys
    assert report["profile"] == "dsrc" and report["samples"] == 20000 and report["direction"] == "downlink"


def test_cli_table_uplink_and_trace_file(capsys, tmp_path: Path) -> None:
    assert main(["link", "validate", "--profile", "lte-v2x", "--direction", "uplink", "--samples", "5000"]) == 0
    out = capsys.readouterr().out
    assert "lte-v2x (uplink)" in out and "p50_ms" in out and "declared" in out and "achieved" in out
    trace = tmp_path / "run.txt"
    header = "pub_time(ms) sub_time(ms) delay(ms)"
    trace.write_text("\n".join([header] + [f"{50 * k} {50 * k + 10 + k % 5} {10 + k % 5}" for k in range(400)]))
    out_json = tmp_path / "report.json"
    assert main(["link", "validate", "--trace", str(trace), "--samples", "5000", "--json", str(out_json)]) == 0
    report = json.loads(out_json.read_text())
    assert report["ks_statistic"] < 0.05 and report["achieved"]["p50_ms"] == 12.0
    assert "KS statistic" in capsys.readouterr().out


def test_cli_errors_and_check(capsys, tmp_path: Path) -> None:
    assert main(["link", "validate", "--profile", "carrier-pigeon"]) == 2
    assert "carrier-pigeon" in capsys.readouterr().err
    bad = tmp_path / "bad.txt"
    bad.write_text("pub_time(ms) sub_time(ms) delay(ms)\n1 2 3\n")
    assert main(["link", "validate", "--trace", str(bad)]) == 2
    assert "delay 3 != sub_time - pub_time" in capsys.readouterr().err
    # --check: exit 1 when a check fails (3 messages cannot show a 50 % loss within 10 %), else 0
    lossy = tmp_path / "lossy.yaml"
    lossy.write_text("name: lossy\nuplink: {delay_ms: 1}\ndownlink: {delay_ms: 1, loss_probability: 0.5}\n")
    assert main(["link", "validate", "--profile", str(lossy), "--samples", "3", "--check"]) == 1
    assert main(["link", "validate", "--profile", str(lossy), "--samples", "3"]) == 0
    assert main(["link", "validate", "--profile", "ideal", "--samples", "100", "--check"]) == 0


def test_link_without_subcommand_still_runs_the_relay() -> None:
    args = build_parser().parse_args(["link", "--rsu-connect", "tcp/127.0.0.1:7447",
                                      "--vehicle-connect", "tcp/127.0.0.1:7448", "--profile", "dsrc"])
    assert args.func is link_cli.run and args.profile == "dsrc" and args.link_command is None
    listed = build_parser().parse_args(["link", "--list-profiles"])
    assert listed.func is link_cli.run and listed.list_profiles
    validate = build_parser().parse_args(["link", "validate", "--profile", "ideal"])
    assert validate.func is link_cli.run_validate


def test_validation_draws_what_the_link_model_draws() -> None:
    profile = load_profile("iaad-field")
    settings = Settings(samples=3000, seed=11)
    for name in ("uplink", "downlink"):
        delays_ms, lost = achieved(getattr(profile, name), settings, name)
        channel = getattr(LinkModel(profile, 11), name)
        send_ns = T0_NS + round(settings.interval_ms * NS_PER_MS) * np.arange(settings.samples)
        fates = [channel.transmit_all(int(t), settings.size_bytes) for t in send_ns]
        assert [not f for f in fates] == lost.tolist()
        # the message's own delivery (a duplicate could only come later in these profiles)
        assert np.allclose([(f[0] - t) / NS_PER_MS for f, t in zip(fates, send_ns) if f], delays_ms)
