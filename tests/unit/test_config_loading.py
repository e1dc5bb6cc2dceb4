"""YAML loading (duplicate keys rejected with file and line) and one-line CLI errors (issue 10, item 14)."""

from __future__ import annotations

import signal
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import BaseModel, Field, ValidationError

from v2i.offline.chaos import ChaosError, load_chaos
from link_emulator.profile import ProfileError, load_profile
from obu_service.config import ObuConfig
from rsu_service.config import RsuConfig
from v2i.runtime.config import ConfigError, UniqueKeyLoader, load_config, parse_yaml, validation_problems
from v2i.sim.maps import bundled_maps, map_path
from v2i.sim.scenario import ScenarioError, load_scenario
from v2i.sim.scenario_site import site_of
from v2i.services import obu_scenario_site
from v2i.cli import main

REPO = Path(__file__).resolve().parents[2]
RLR = REPO / "src" / "v2i" / "sim" / "scenarios" / "red-light-runner.yaml"


def _strict(text: str):
    return yaml.load(text, Loader=UniqueKeyLoader)  # noqa: S506 (a SafeLoader subclass)


# ---- the loader ---------------------------------------------------------------------------

@pytest.mark.parametrize(
    ("text", "key", "line", "first"),
    [
        ("rsu: 1\nname: x\nrsu: 2\n", "rsu", 3, 1),  # top level
        ("a:\n  b: 1\n  c: 2\n  b: 3\n", "b", 4, 2),  # nested
        ("events:\n  - {at_s: 1, at_s: 2}\n", "at_s", 2, 2),  # flow mapping in a list, same line
        ("x:\n  - y: 1\n    z:\n      w: 1\n      w: 1\n", "w", 5, 4),  # deep, equal values too
        ("1: a\n0x1: b\n", 1, 2, 1),  # different spellings of one key
    ],
)
def test_duplicate_key_names_file_line_and_first_line(text, key, line, first) -> None:
    with pytest.raises(ConfigError) as info:
        parse_yaml(text, "some/file.yaml")
    assert str(info.value) == f"some/file.yaml:{line}: duplicate key {key!r} (first at line {first})"


def test_merge_keys_still_override() -> None:
    assert _strict("base: &b {x: 1, y: 2}\nc:\n  <<: *b\n  y: 3\n")["c"] == {"x": 1, "y": 3}


_KEYS = st.text(alphabet="abcdefgh_", min_size=1, max_size=6)
_TREES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(_KEYS, inner, max_size=4),
    max_leaves=20,
)


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(_KEYS, _TREES, min_size=1, max_size=5))
def test_same_data_as_safe_load_without_duplicates(data) -> None:
    text = yaml.safe_dump(data)
    assert _strict(text) == yaml.safe_load(text) == data


@settings(max_examples=100, deadline=None)
@given(st.dictionaries(_KEYS, st.integers(), min_size=1, max_size=6), st.data())
def test_any_repeated_key_is_rejected(data, draw) -> None:
    key = draw.draw(st.sampled_from(sorted(data)))
    text = yaml.safe_dump(data) + f"{key}: 0\n"  # safe_load would keep this last value silently
    assert yaml.safe_load(text)[key] == 0
    with pytest.raises(ConfigError, match=rf"f\.yaml:{len(data) + 1}: duplicate key '{key}'"):
        parse_yaml(text, "f.yaml")


def test_every_shipped_yaml_has_unique_keys() -> None:
    listed = subprocess.run(["git", "ls-files", "*.yaml", "*.yml"], cwd=REPO, capture_output=True, text=True)
    files = listed.stdout.split()
    assert len(files) >= 13  # scenarios, profiles, chaos examples, deploy files
    for name in files:
        parse_yaml((REPO / name).read_text(encoding="utf-8"), name)


def test_syntax_error_is_one_line_with_file_line_and_column() -> None:
    with pytest.raises(ConfigError) as info:
        parse_yaml("name: [a, b\n", "bad.yaml")
    message = str(info.value)
    assert message.startswith("bad.yaml:2:1: invalid YAML: expected ',' or ']'")
    assert "line 1" in message and "\n" not in message


# ---- every loader uses it -----------------------------------------------------------------

def _with_second_rsu(tmp_path: Path) -> tuple[Path, int, int]:
    """A copy of red-light-runner with a second ``rsu:`` appended: (path, its line, first line)."""
    lines = RLR.read_text(encoding="utf-8").splitlines()
    first = lines.index("rsu:") + 1
    path = tmp_path / "two-rsus.yaml"
    path.write_text("\n".join([*lines, "rsu:", "  id: other", "  position: {x: 0, y: 0}", "  yaw_deg: 0"]) + "\n")
    return path, len(lines) + 1, first


def test_scenario_with_two_rsu_sections_is_rejected(tmp_path) -> None:
    path, line, first = _with_second_rsu(tmp_path)
    with pytest.raises(ScenarioError) as info:
        load_scenario(str(path))
    assert str(info.value) == f"{path}:{line}: duplicate key 'rsu' (first at line {first})"


@pytest.mark.parametrize(
    ("load", "error", "text"),
    [
        (load_profile, ProfileError, "name: p\nuplink: {delay_ms: 1}\ndownlink: {delay_ms: 1, delay_ms: 2}\n"),
        (load_chaos, ChaosError, "name: c\nevents:\n  - {at_s: 1, outage: {duration_s: 1, duration_s: 9}}\n"),
        (lambda p: load_config(RsuConfig, p), ConfigError, "seed: 1\nrsu_id: a\nrsu_id: b\n"),
    ],
    ids=["profile", "chaos", "service-config"],
)
def test_other_loaders_reject_duplicates(tmp_path, load, error, text) -> None:
    path = tmp_path / "dup.yaml"
    path.write_text(text)
    with pytest.raises(error, match=rf"^{path}:3: duplicate key"):
        load(path)


# ---- pydantic summaries -------------------------------------------------------------------

class _Model(BaseModel):
    a: int = Field(gt=0)
    b: int = Field(gt=0)
    c: int = Field(gt=0)
    d: int = Field(gt=0)


def test_validation_problems_one_line_renamed_and_capped() -> None:
    with pytest.raises(ValidationError) as info:
        _Model(a=0, b=0, c=0, d=0)
    text = validation_problems(info.value, names={"a": "--a-flag"})
    assert text == ("--a-flag: Input should be greater than 0; b: Input should be greater than 0; "
                    "c: Input should be greater than 0; and 1 more")


def test_model_validator_error_has_no_pydantic_prefix() -> None:
    with pytest.raises(ValidationError) as info:
        ObuConfig(fusion="iou-merge", compensation="oosm")
    assert validation_problems(info.value) == "compensation 'oosm' needs a filter to re-run: use it with --fusion kf"


# ---- lane compensation needs a map -------------------------------------------------------

def test_lane_without_map_says_which_map_and_where(tmp_path) -> None:
    scenario = tmp_path / "custom.yaml"
    shutil.copy(RLR, scenario)
    config = ObuConfig(compensation="lane", scenario=str(scenario))
    with pytest.raises(ValueError) as info:
        obu_scenario_site(config)
    message = str(info.value)
    assert str(tmp_path / "custom.osm") in message and "beside the scenario YAML" in message
    assert all(name in message for name in bundled_maps()) and "\n" not in message
    with pytest.raises(ValueError, match="Lanelet2 map"):  # a site without a map, however it was made
        config.lanes(site_of(load_scenario(scenario)))
    shutil.copy(map_path("red-light-runner"), tmp_path / "custom.osm")  # as the message says: picked up
    _, site = obu_scenario_site(config)
    assert config.lanes(site) is not None


# ---- the CLI: one line on stderr, exit code 2 ----------------------------------------------

@pytest.fixture
def bad_files(tmp_path) -> Path:
    (tmp_path / "dup.yaml").write_text(_with_second_rsu(tmp_path)[0].read_text())
    (tmp_path / "syntax.yaml").write_text("name: [a, b\n")
    (tmp_path / "list.yaml").write_text("- a\n- b\n")
    (tmp_path / "empty.yaml").write_text("")
    (tmp_path / "binary.yaml").write_bytes(b"\x00\xff\xfe garbage \x80")
    (tmp_path / "negative.yaml").write_text(RLR.read_text().replace("duration_s: 30.0", "duration_s: -3"))
    shutil.copy(RLR, tmp_path / "nomap.yaml")
    (tmp_path / "profile.yaml").write_text("name: p\nuplink: {delay_ms: -1}\ndownlink: {delay_ms: 1}\n")
    (tmp_path / "chaos-dup.yaml").write_text("name: c\nevents:\n  - {at_s: 1, outage: {duration_s: 1}}\n"
                                             "events: []\n")
    (tmp_path / "chaos-field.yaml").write_text("name: c\nevents:\n  - {at_s: -1, outage: {duration_s: 1}}\n")
    (tmp_path / "chaos-profile.yaml").write_text("name: c\nevents:\n  - {at_s: 1, profile: my.yaml}\n")
    (tmp_path / "config-dup.yaml").write_text("seed: 1\nseed: 2\n")
    (tmp_path / "config-field.yaml").write_text("seed: 1\nwarp: 9\n")
    (tmp_path / "a-file").write_text("")
    return tmp_path


CLI_ERRORS = [
    # (argv, text the line must contain); {d} is the folder of bad files
    ("eval --scenario no-such-place", "unknown scenario 'no-such-place'"),
    ("eval --scenario {d}/dup.yaml", "dup.yaml:"),
    ("eval --scenario {d}/syntax.yaml", "syntax.yaml:2:1: invalid YAML"),
    ("eval --scenario {d}/list.yaml", "must be a mapping, got list"),
    ("eval --scenario {d}/empty.yaml", "empty.yaml is empty"),
    ("eval --scenario {d}/binary.yaml", "not UTF-8"),
    ("eval --scenario {d}/negative.yaml", "negative.yaml: duration_s: Input should be greater than 0"),
    ("eval --scenario {d}/nomap.yaml --compensation lane", "nomap.osm does not exist"),
    ("eval --profile carrier-pigeon", "unknown link profile 'carrier-pigeon'"),
    ("eval --profile {d}/profile.yaml", "profile.yaml: uplink.delay_ms"),
    ("eval --duration -5", "--duration must be a finite number > 0, got -5"),
    ("eval --duration 0", "--duration must be"),
    ("eval --duration nan", "--duration must be"),
    ("eval --duration soon", "argument --duration: invalid float value"),
    ("eval --seed -1", "--seed: Input should be greater than or equal to 0"),
    ("eval --deadline-ms 0", "--deadline-ms: Input should be greater than 0"),
    ("eval --rsu-clock-drift-ppm 5000", "--rsu-clock-drift-ppm: Input should be less than or equal to 1000"),
    ("eval --rsu-clock-step-at-s -1", "--rsu-clock-step-at-s"),
    ("eval --fusion iou-merge --compensation oosm", "use it with --fusion kf"),
    ("eval --fusion magic", "argument --fusion: invalid choice"),
    ("eval --json {d}/no-folder/out.json", "folder"),
    ("eval --json {d}", "is a directory"),
    ("eval --chaos {d}/missing.yaml", "cannot read chaos timeline"),
    ("eval --chaos {d}/chaos-dup.yaml", "chaos-dup.yaml:4: duplicate key 'events' (first at line 2)"),
    ("eval --chaos {d}/chaos-field.yaml", "events.0.at_s"),
    ("eval --table seeds --seeds 0", "--seeds must be"),
    ("eval --table seeds --workers -2", "--workers must be"),
    ("eval --table seeds --report {d}/a-file/sub", "a-file is a file"),
    ("demo --startup -1", "--startup must be"),
    ("demo --kill-link-at -3", "--kill-link-at must be a finite number >= 0"),
    ("demo --link-down-s 0", "--link-down-s must be"),
    ("demo --scenario {d}/dup.yaml", "duplicate key 'rsu'"),
    ("chaos run {d}/missing.yaml", "cannot read chaos timeline"),
    ("chaos run {d}/chaos-profile.yaml", "is not bundled"),
    ("chaos run {d}/chaos-dup.yaml --duration -1", "--duration must be"),
    ("chaos", "required"),
    ("teleport", "invalid choice"),
    ("rsu --config {d}/config-dup.yaml", "config-dup.yaml:2: duplicate key 'seed' (first at line 1)"),
    ("rsu --config {d}/config-field.yaml", "config-field.yaml and command line): warp: Extra inputs"),
    ("rsu --config {d}/missing.yaml", "cannot read config"),
    ("rsu --duration -1", "duration_s: Input should be greater than 0"),
    ("rsu --scenario {d}/syntax.yaml", "invalid YAML"),
    ("rsu --listen nonsense", "Zenoh: Endpoints must be of the form"),
    ("obu --compensation lane --scenario {d}/nomap.yaml", "beside the scenario YAML"),
    ("obu --vehicle-id a.b", "vehicle_id: invalid id"),
    ("link --rsu-connect tcp/127.0.0.1:1 --vehicle-connect tcp/127.0.0.1:2 --profile {d}/dup.yaml",
     "duplicate key 'rsu'"),
    ("link --config {d}/list.yaml", "must be a mapping"),
    ("link validate --trace {d}/missing.txt", "trace: cannot read trace"),
    ("link validate --profile {d}/profile.yaml", "uplink.delay_ms"),
    ("link validate --samples 0", "--samples: must be >= 1"),
    ("link set --connect tcp/127.0.0.1:1 --loss 3 --for 1", "loss_probability"),
]


@pytest.fixture
def restore_signals():
    """Services install SIGINT/SIGTERM handlers; give pytest its own back."""
    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    yield
    for sig, handler in saved.items():
        signal.signal(sig, handler)


@pytest.mark.parametrize(("argv", "expected"), CLI_ERRORS, ids=[a for a, _ in CLI_ERRORS])
def test_cli_error_is_one_line_and_exit_2(argv, expected, bad_files, capsys, restore_signals) -> None:
    try:
        code = main(argv.format(d=bad_files).split())
    except SystemExit as exc:  # argparse usage errors exit from parse_args
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and err.endswith("\n"), err
    assert expected in err and "Traceback" not in err
