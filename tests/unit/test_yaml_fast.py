"""The libyaml loader (``FastUniqueKeyLoader``) reads what the pure-Python one reads, rejects the
same duplicate keys, and the parse cache of ``load_bundled_or_file`` never serves stale data."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from v2i.runtime import config
from v2i.runtime.config import FastUniqueKeyLoader, UniqueKeyLoader
from v2i.sim.scenario import ScenarioError, bundled_scenarios, load_scenario

REPO = Path(__file__).resolve().parents[2]
RLR = REPO / "src" / "v2i" / "sim" / "scenarios" / "red-light-runner.yaml"


def _load(text: str, loader: type):
    return yaml.load(text, Loader=loader)


def test_fast_loader_is_libyaml_where_pyyaml_has_it() -> None:
    if not hasattr(yaml, "CSafeLoader"):
        pytest.skip("PyYAML built without libyaml")
    assert issubclass(FastUniqueKeyLoader, yaml.CSafeLoader)


def test_fast_and_pure_loaders_agree_on_every_shipped_yaml() -> None:
    listed = subprocess.run(["git", "ls-files", "*.yaml", "*.yml"], cwd=REPO, capture_output=True, text=True, check=True)
    files = listed.stdout.split()
    assert len(files) >= 13
    for name in files:
        text = (REPO / name).read_text(encoding="utf-8")
        assert _load(text, FastUniqueKeyLoader) == _load(text, UniqueKeyLoader), name


_SCALARS = st.one_of(st.integers(), st.floats(allow_nan=False), st.booleans(), st.none(), st.text(max_size=8))
_KEYS = st.text(alphabet="abcxyz_", min_size=1, max_size=5)
_DOCS = st.recursive(_SCALARS, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(_KEYS, inner, max_size=4),
                     max_leaves=20)


@settings(max_examples=150, deadline=None)
@given(_DOCS, st.booleans())
def test_fast_and_pure_loaders_agree_on_generated_documents(doc, flow) -> None:
    text = yaml.safe_dump(doc, default_flow_style=flow)
    assert _load(text, FastUniqueKeyLoader) == _load(text, UniqueKeyLoader) == doc


@pytest.mark.parametrize("text", ["rsu: 1\nname: x\nrsu: 2\n", "a:\n  b: 1\n  c: 2\n  b: 3\n",
                                  "events:\n  - {at_s: 1, at_s: 2}\n", "1: a\n0x1: b\n"])
def test_fast_loader_rejects_duplicate_keys(text) -> None:
    with pytest.raises(config.DuplicateKeyError):
        _load(text, FastUniqueKeyLoader)


def test_edited_scenario_file_is_parsed_again(tmp_path) -> None:
    path = tmp_path / "s.yaml"
    text = RLR.read_text(encoding="utf-8")
    path.write_text(text)
    first = load_scenario(str(path))
    assert load_scenario(str(path)) == first  # served from the parse cache, equal
    path.write_text(text.replace(f"duration_s: {first.duration_s}\n", "duration_s: 7.5\n", 1))
    assert load_scenario(str(path)).duration_s == 7.5
    path.write_text(text + "name: again\n")
    with pytest.raises(ScenarioError, match="duplicate key 'name'"):
        load_scenario(str(path))


def test_bundled_scenarios_load_equal_twice() -> None:
    for name in bundled_scenarios():
        assert load_scenario(name) == load_scenario(name)
        assert load_scenario(name).model_dump() == load_scenario(name).model_dump()
