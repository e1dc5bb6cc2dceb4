"""The Site (``v2i.runtime.site``): a site file loads, a bad field is named, a scenario's site is its
RSUs and vehicles; the services configured by a site file load no scenario and no simulator."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from obu_service.config import ObuConfig
from rsu_service.config import RsuConfig
from v2i.runtime.site import SiteError, load_site
from v2i.sim.maps import map_path
from v2i.sim.scenario import bundled_scenarios, load_scenario
from v2i.sim.scenario_site import scenario_site

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "site.yaml"


def test_the_example_site_loads():
    site = load_site(EXAMPLE)
    assert site.name == "example-site" and (site.origin.lat_deg, site.origin.lon_deg) == (49.0, 8.4)
    assert site.rsu("rsu1").xy == (60.0, 10.0) and site.rsu("rsu1").rate_hz == 5.0
    assert site.rsu("any-id") is site.rsus[0]  # the only RSU, whatever id the service runs with
    assert site.vehicle("ego").size_m == (4.6, 1.9, 1.5) and site.vehicle("ego").lidar_rate_hz == 10.0
    assert site.map is None


def _site_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "site.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(("change", "field"), [
    (("rate_hz: 5.0", "rate_hz: -5.0"), "rsus.0.rate_hz"),
    (("id: rsu1", "id: rsu 1"), "rsus.0.id"),
    (("size_m: [4.6, 1.9, 1.5]", "size_m: [4.6, 1.9]"), "vehicles.0.size_m"),
    (("lat_deg: 49.0", "lat_deg: 95.0"), "origin.lat_deg"),
    (("name: example-site", "name: example-site\nrsu_count: 1"), "rsu_count"),
    (("# map: example.osm", "map: nowhere.osm"), "map"),
])
def test_a_bad_field_is_named(tmp_path, change, field):
    path = _site_file(tmp_path, EXAMPLE.read_text().replace(*change))
    with pytest.raises(SiteError) as info:
        load_site(path)
    assert f"site {path}" in str(info.value) and f": {field}" in str(info.value)


def test_a_repeated_id_and_an_unreadable_file_are_errors(tmp_path):
    text = EXAMPLE.read_text()
    rsu = text[text.index("  - id: rsu1"):text.index("vehicles:")]
    with pytest.raises(SiteError, match="RSU ids must be unique"):
        load_site(_site_file(tmp_path, text.replace("vehicles:", rsu + "vehicles:")))
    with pytest.raises(SiteError, match="cannot read site"):
        load_site(tmp_path / "missing.yaml")


def test_the_map_is_relative_to_the_site_file(tmp_path):
    (tmp_path / "maps").mkdir()
    (tmp_path / "maps" / "here.osm").write_bytes(map_path("red-light-runner").read_bytes())
    site = load_site(_site_file(tmp_path, EXAMPLE.read_text().replace("# map: example.osm", "map: maps/here.osm")))
    assert site.map == tmp_path / "maps" / "here.osm"


@pytest.mark.parametrize("name", bundled_scenarios())
def test_a_scenarios_site_is_its_rsus_and_vehicles(name):
    scenario, site = load_scenario(name), scenario_site(name)
    assert site.name == scenario.name
    assert [(r.id, r.xy, r.position.z, r.yaw_deg, r.rate_hz, r.range_m) for r in site.rsus] == \
        [(r.id, (r.position.x, r.position.y), r.position.z, r.yaw_deg, r.rate_hz, r.range_m) for r in scenario.rsus]
    assert [(v.id, v.size_m, v.lidar_rate_hz) for v in site.vehicles] == \
        [(v.name, v.size, v.lidar.rate_hz) for v in scenario.vehicles]
    assert (site.map is not None) == (name != "two-rsu-corridor") or site.map == map_path(name)


def test_a_site_goes_with_an_outside_source_and_no_scenario():
    assert RsuConfig(site=str(EXAMPLE), source="zenoh").site == str(EXAMPLE)
    with pytest.raises(ValueError, match="not both"):
        RsuConfig(site=str(EXAMPLE), scenario="red-light-runner", source="zenoh")
    with pytest.raises(ValueError, match="simulates a scenario"):
        RsuConfig(site=str(EXAMPLE))  # --source sim, the default
    with pytest.raises(ValueError, match="simulates a scenario"):
        ObuConfig(site=str(EXAMPLE), source="sim")


def test_services_on_a_site_file_load_no_scenario_and_no_simulator():
    """The nodes ``v2i rsu|obu --site FILE --source zenoh`` run, built as the command builds them."""
    code = ("import sys\nfrom obu_service.config import ObuConfig\nfrom rsu_service.config import RsuConfig\n"
            "from v2i.services import obu_node, rsu_node\n"
            f"rsu = rsu_node(RsuConfig(site={str(EXAMPLE)!r}, source='zenoh'))\n"
            f"obu = obu_node(ObuConfig(site={str(EXAMPLE)!r}, source='zenoh'))\n"
            "assert rsu.duration_s is None and obu.duration_s is None  # until stopped\n"
            "assert obu.pipeline.config.known_rsus == {'rsu1': (60.0, 10.0)}\n"
            "assert obu.pipeline.config.ego_size_m == (4.6, 1.9)\n"
            "print('LOADED', sorted(m for m in sys.modules if m.startswith('v2i.sim')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert ast.literal_eval(out.rsplit("LOADED ", 1)[1]) == []


def test_the_link_takes_its_rsus_position_from_a_site(tmp_path):
    from link_emulator.cli import site_rsu_position
    from v2i.runtime.config import ConfigError

    assert site_rsu_position(str(EXAMPLE), None) == site_rsu_position(str(EXAMPLE), "rsu1") == (60.0, 10.0)
    assert site_rsu_position(None, None) is None
    text = EXAMPLE.read_text()
    second = text[text.index("  - id: rsu1"):text.index("vehicles:")].replace("rsu1", "rsu2").replace("60.0", "-60.0")
    two = _site_file(tmp_path, text.replace("vehicles:", second + "vehicles:"))
    assert site_rsu_position(str(two), "rsu2") == (-60.0, 10.0)
    with pytest.raises(ConfigError, match="--rsu-id"):
        site_rsu_position(str(two), None)
    with pytest.raises(ConfigError, match="no RSU 'rsu3'"):
        site_rsu_position(str(two), "rsu3")
