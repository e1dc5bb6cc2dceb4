"""Shipped link profiles, profile validation errors and CICV5G trace parsing (pure)."""

from __future__ import annotations

import fnmatch
import gzip
import tomllib
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from link_emulator.profile import ProfileError, bundled_profiles, load_profile
from link_emulator.trace import (
    TraceError,
    bundled_traces,
    load_trace,
    mean_run_length,
    parse_cicv5g,
)
from link_emulator.validate import Settings, declared

REQUIRED = {"ideal", "dsrc", "lte-v2x", "cellular-uu", "5g-uu-trace", "congested", "iaad-field", "otvic-field"}
PROFILE_DIR = resources.files("link_emulator") / "profiles"
REPO = Path(__file__).resolve().parents[2]
HEADER = "pub_time(ms) sub_time(ms) delay(ms) utmX(m) utmY(m) heading(rad) velocity(m/s) cellid(db) sinr(db) rsrp(db)"


def _row(pub_ms: int, delay_ms: int) -> str:
    return f"{pub_ms} {pub_ms + delay_ms} {delay_ms} 1.0 2.0 0.1 5.0 5C422503D 15 -98"


def test_every_required_profile_is_shipped_and_loads() -> None:
    assert REQUIRED <= set(bundled_profiles())
    for name in bundled_profiles():
        profile = load_profile(name)
        assert profile.name == name and profile.description


@pytest.mark.parametrize("name", sorted(REQUIRED - {"ideal"}))
def test_shipped_profiles_cite_their_sources_and_no_local_paths(name: str) -> None:
    text = (PROFILE_DIR / f"{name}.yaml").read_text()
    comments = [line for line in text.splitlines() if line.lstrip().startswith("#")]
    assert len(comments) >= 5, "a profile explains where its numbers come from"
    assert "/work/" not in text and "shared/" not in text
    numbers_lines = [line for line in text.splitlines() if ":" in line and any(c.isdigit() for c in line.split(":")[-1])
                     and not line.lstrip().startswith("#") and "name:" not in line and "description:" not in line]
    assert all("#" in line for line in numbers_lines if "trace:" not in line), "each number carries a source comment"


def test_seed_papers_are_cited_by_author_and_title() -> None:
    assert "Liu et al." in (PROFILE_DIR / "lte-v2x.yaml").read_text()
    assert "The Necessity of Adaptive Data Fusion" in (PROFILE_DIR / "iaad-field.yaml").read_text()
    assert "OTVIC" in (PROFILE_DIR / "otvic-field.yaml").read_text()
    assert "zenodo.17475688" in (PROFILE_DIR / "5g-uu-trace.yaml").read_text()


def test_lte_v2x_stays_a_15_to_35_ms_link_with_median_about_22_ms() -> None:
    down = load_profile("lte-v2x").downlink
    summary, _ = declared(down, Settings())
    assert 21.5 <= summary.p50_ms <= 22.5
    assert down.jitter.quantile_ms(down.delay_ms, 0.9) < 36.0
    # the red-light-runner RSU is within ~30 m: no distance loss there
    assert float(down.pdr_at(30.0)) == 1.0


def test_distance_pdr_of_radio_profiles_matches_the_sources() -> None:
    dsrc, lte = load_profile("dsrc").downlink, load_profile("lte-v2x").downlink
    total = lambda d, m: float(m.pdr_at(d)) * (1.0 - m.loss_probability)
    assert total(100.0, dsrc) == pytest.approx(0.97, abs=0.01)
    assert total(500.0, dsrc) == pytest.approx(0.10, abs=0.01)
    assert total(1200.0, dsrc) == 0.0
    for distance_m, pdr in ((100.0, 0.98), (300.0, 0.95), (500.0, 0.65)):
        assert total(distance_m, lte) == pytest.approx(pdr, abs=0.015)


def test_shipped_traces_are_package_data_with_licence_and_citation() -> None:
    data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["link_emulator"]
    root = resources.files("link_emulator")
    shipped = [f"traces/{name}" for name in bundled_traces()] + ["traces/README.md"]
    shipped += [f"profiles/{p}.yaml" for p in bundled_profiles()]
    for path in shipped:
        assert (root / path).is_file()
        assert any(fnmatch.fnmatch(path, pattern) for pattern in data), path
    readme = (root / "traces" / "README.md").read_text()
    assert "CC BY 4.0" in readme and "10.5281/zenodo.17475688" in readme
    assert "cicv5g/urban_n78_v20_run01.txt.gz" in bundled_traces()


def test_bundled_trace_statistics() -> None:
    trace = load_trace("cicv5g/urban_n78_v20_run01.txt.gz")
    assert trace.period_ms == 55.0
    assert np.median(trace.delay_ms) == 15.0 and np.percentile(trace.delay_ms, 99) == 25.0
    assert trace.delay_ms.max() == 269.0
    assert trace.loss_ratio == pytest.approx(0.038, abs=0.001)


# ---- profile errors name the field -----------------------------------------------------------


def _write(tmp_path: Path, downlink: str) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text(f"name: bad\nuplink: {{delay_ms: 1}}\ndownlink: {downlink}\n")
    return path


@pytest.mark.parametrize(
    ("downlink", "field"),
    [
        ("{delay_ms: 1, correlation: 1.0}", "downlink.correlation"),
        ("{delay_ms: 1, mean_burst_len: 0.5}", "downlink.mean_burst_len"),
        ("{delay_ms: 1, pdr_curve: [[100, 0.9], [50, 0.8]]}", "downlink.pdr_curve"),
        ("{delay_ms: 1, pdr_curve: [[0, 1.2]]}", "downlink.pdr_curve"),
        ("{delay_ms: 1, range_m: 0}", "downlink.range_m"),
        ("{delay_ms: 1, bandwidth_kbps: -5}", "downlink.bandwidth_kbps"),
        ("{delay_ms: 1, queue_limit_ms: 10}", "queue_limit_ms needs bandwidth_kbps"),
        ("{delay_ms: 1, duplicate_probability: 2}", "downlink.duplicate_probability"),
        ("{delay_ms: 1, fifo: maybe}", "downlink.fifo"),
        ("{delay_ms: 1, outage: {mode: later}}", "downlink.outage.mode"),
        ("{delay_ms: 1, outage: {windows_s: [[5, 2]]}}", "downlink.outage.windows_s"),
        ("{delay_ms: 1, outage: {mean_interval_s: 5}}", "mean_interval_s and duration_s go together"),
        ("{delay_ms: 1, outage: {mean_interval_s: 5, duration_s: [2, 1]}}", "downlink.outage.duration_s"),
        ("{delay_ms: 1, spikes: {probability: 0.1}}", "downlink.spikes.extra"),
        ("{delay_ms: 1, jitter: {distribution: pareto, scale_ms: 1, shape: 0}}", "downlink.jitter.pareto.shape"),
        ("{delay_ms: 1, jitter: {distribution: empirical}}", "downlink.jitter.empirical"),
        ("{delay_ms: 1, jitter: {distribution: empirical, samples_ms: []}}", "downlink.jitter.empirical.samples_ms"),
        ("{delay_ms: 1, replay: {trace: no-such-trace.txt}}", "downlink.replay.trace"),
        ("{delay_ms: 1, bandwidth: 3}", "downlink.bandwidth"),
    ],
)
def test_bad_profile_fields_are_named(tmp_path: Path, downlink: str, field: str) -> None:
    path = _write(tmp_path, downlink)
    with pytest.raises(ProfileError, match=field.replace(".", r"\.")) as info:
        load_profile(path)
    assert str(path) in str(info.value)


def test_a_new_profile_needs_no_code(tmp_path: Path) -> None:
    trace = tmp_path / "t.txt"
    trace.write_text("\n".join([HEADER] + [_row(1000 + 50 * k, 10 + k % 3) for k in range(20)]) + "\n")
    path = _write(tmp_path, "{delay_ms: 2, jitter: {distribution: empirical, samples_ms: [1, 2, 3]}, "
                            f"replay: {{trace: {trace}}}, fifo: true, duplicate_probability: 0.1}}")
    profile = load_profile(path)
    assert profile.downlink.replay.trace == str(trace)
    assert profile.downlink.jitter.sorted_ms.tolist() == [1.0, 2.0, 3.0]


# ---- CICV5G trace parsing -------------------------------------------------------------------


def test_trace_gaps_become_lost_slots() -> None:
    pubs = [0, 50, 100, 200, 250, 400, 450]  # gaps of 100 ms (1 lost) and 150 ms (2 lost)
    trace = parse_cicv5g("\n".join([HEADER] + [_row(p, 10) for p in pubs]), "test")
    assert trace.period_ms == 50.0
    assert trace.loop_ms == 500.0  # the loop closes one period after the last row
    assert trace.lost_after.tolist() == [0, 0, 1, 0, 2, 0, 0]
    assert trace.own_slot_ms.tolist() == [50.0] * 7
    assert trace.loss_ratio == pytest.approx(0.3)  # 3 lost periods of a 500 ms loop
    assert trace.mean_burst_len == pytest.approx(1.5)
    assert trace.overtaken_ratio == 0.0


def test_mean_run_length() -> None:
    assert mean_run_length(np.array([], dtype=bool)) == 0.0
    assert mean_run_length(np.array([0, 0, 0], dtype=bool)) == 0.0
    assert mean_run_length(np.array([1, 1, 0, 1, 0, 1, 1, 1], dtype=bool)) == pytest.approx(2.0)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "empty file"),
        ("time delay\n1 2\n", "header lacks column"),
        (f"{HEADER}\n{_row(0, 10)}\n", "at least 2 data rows"),
        (f"{HEADER}\n{_row(0, 10)}\n50 60\n", "line 3: expected at least 3 columns"),
        (f"{HEADER}\n{_row(0, 10)}\n50 sixty 10\n", "line 3: pub_time, sub_time and delay must be numbers"),
        (f"{HEADER}\n{_row(0, 10)}\n50 60 25\n", "line 3: delay 25 != sub_time - pub_time = 10"),
        (f"{HEADER}\n{_row(0, 10)}\n50 40 -10\n", "line 3: negative delay"),
        (f"{HEADER}\n{_row(100, 10)}\n{_row(50, 10)}\n", "line 3: pub_time not after"),
        (f"{HEADER}\n{_row(0, 10)}\nnan nan nan\n", "line 3: non-finite"),
    ],
)
def test_malformed_traces_are_rejected_clearly(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "trace.txt"
    path.write_text(text)
    with pytest.raises(TraceError, match=message.replace("(", r"\(").replace(")", r"\)")) as info:
        load_trace(str(path))
    assert str(path) in str(info.value)


def test_unreadable_and_undecodable_traces(tmp_path: Path) -> None:
    with pytest.raises(TraceError, match="not a bundled trace"):
        load_trace(str(tmp_path / "missing.txt"))
    bad = tmp_path / "bad.txt.gz"
    bad.write_bytes(b"not gzip at all")
    with pytest.raises(TraceError, match="cannot decode"):
        load_trace(str(bad))
    good = tmp_path / "good.txt.gz"
    good.write_bytes(gzip.compress(f"{HEADER}\n{_row(0, 10)}\n{_row(50, 12)}\n".encode()))
    assert load_trace(str(good)).delay_ms.tolist() == [10.0, 12.0]
