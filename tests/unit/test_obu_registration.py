"""Which RSUs an OBU registers (``ObuConfig.registration``, ``--known-rsus``), what the site PKI
certifies (``v2i.security.pki_registry``) and what the OBU says at start (``obu_service.cli``)."""

from __future__ import annotations

import argparse

import pytest

from obu_service import cli
from obu_service.config import ObuConfig
from obu_service.pipeline import ObuPipeline
from obu_service.rsu_table import MAX_RSUS
from v2i.runtime.config import load_config
from v2i.runtime.site import Site
from v2i.security.attacker_keys import prepare_attacker_pki
from v2i.security.pki import Pki, read_cert
from v2i.security.pki_registry import certified_rsu_ids, certified_rsus, unregistered_warnings
from v2i.security.site import write_site

NOW_NS = 1_767_225_600 * 10**9
NW, SE = (-3.5, 8.5), (40.0, -12.0)


def site(*rsus: tuple[str, tuple[float, float]]) -> Site:
    """A site of these RSUs (id, map x/y) and the vehicle ego."""
    return Site.model_validate({
        "name": "test-site", "origin": {"lat_deg": 49.0, "lon_deg": 8.4},
        "rsus": [{"id": rsu_id, "position": {"x": x, "y": y}} for rsu_id, (x, y) in rsus],
        "vehicles": [{"id": "ego", "size_m": [4.6, 1.9, 1.5]}]})


def obu_from_cli(*argv: str) -> ObuConfig:
    """The ObuConfig ``v2i obu ARGV`` runs with (its flags as ``run_service`` passes them)."""
    parser = argparse.ArgumentParser()
    cli.configure_parser(parser)
    args = parser.parse_args(list(argv))
    return load_config(ObuConfig, None, {f: getattr(args, f) for f in ObuConfig.model_fields if hasattr(args, f)})


@pytest.fixture
def readme_pki(tmp_path):
    """The README's ``v2i pki site pki --rsu rsu1 --vehicle ego``."""
    return write_site(tmp_path / "pki", NOW_NS, rsu_ids=["rsu1"], vehicle_ids=["ego"])


# --- the README's recipe: RSU rsu1 on a scenario whose only RSU is rsu-nw ---------------------

def test_the_readme_obu_registers_the_rsu_its_pki_certifies_where_the_site_places_it(readme_pki):
    config = obu_from_cli("--pki", str(readme_pki))
    rsus = config.registered_rsus(site(("rsu-nw", NW)))
    assert rsus == {"rsu-nw": NW, "rsu1": NW}  # rsu1 runs the single-RSU site's RSU (Site.rsu)
    assert ObuPipeline(config.pipeline_config(site(("rsu-nw", NW)))).config.known_rsus == rsus
    assert cli.registration_lines(config, rsus) == [
        "registered RSUs (from the site and the RSU certificates of --pki; served first, always admitted): "
        "rsu-nw at (-3.5, 8.5), rsu1 at (-3.5, 8.5)"]


def test_without_a_pki_the_obu_registers_the_sites_rsus():
    config = obu_from_cli()
    assert config.registered_rsus(site(("rsu-nw", NW), ("rsu-se", SE))) == {"rsu-nw": NW, "rsu-se": SE}
    assert cli.registration_lines(config, {"rsu-nw": NW}) == [
        "registered RSUs (from the site; served first, always admitted): rsu-nw at (-3.5, 8.5)"]


# --- --known-rsus ---------------------------------------------------------------------------

def test_known_rsus_from_the_cli_are_exactly_those_placed_by_the_site(readme_pki):
    config = obu_from_cli("--known-rsus", " rsu1, rsu-se ,", "--pki", str(readme_pki))
    assert config.known_rsus == {"rsu1": None, "rsu-se": None}
    assert config.registered_rsus(site(("rsu-nw", NW), ("rsu-se", SE), ("rsu1", (1.0, 2.0)))) == {
        "rsu1": (1.0, 2.0), "rsu-se": SE}  # neither the site's rsu-nw nor anything else
    assert obu_from_cli("--known-rsus", "rsu1").registered_rsus(site(("rsu-nw", NW))) == {"rsu1": NW}


def test_a_known_rsu_the_site_cannot_place_needs_a_position():
    two = site(("rsu-nw", NW), ("rsu-se", SE))
    with pytest.raises(ValueError, match=r"site 'test-site' has no RSU 'rsu1' \(its RSUs: \['rsu-nw', 'rsu-se'\]\)"):
        obu_from_cli("--known-rsus", "rsu1").registered_rsus(two)
    placed = ObuConfig.model_validate({"known_rsus": {"rsu1": [5, 6], "rsu-se": None}})
    assert placed.registered_rsus(two) == {"rsu1": (5.0, 6.0), "rsu-se": SE}
    assert obu_from_cli("--known-rsus", ",").registered_rsus(two) == {}  # none registered: all unknown


@pytest.mark.parametrize("bad, message", [(["rsu1", "rsu1"], "given twice"), (["rsu 1"], "invalid id"),
                                          ([1, 2], "valid dictionary"), ({"rsu1": [1]}, "Field required")])
def test_bad_known_rsus_are_refused_naming_the_field(bad, message):
    with pytest.raises(ValueError, match=message) as info:
        ObuConfig.model_validate({"known_rsus": bad})
    assert "known_rsus" in str(info.value)


# --- what the PKI certifies -------------------------------------------------------------------

def test_a_certificate_certifies_the_rsus_whose_lists_its_keys_cover(tmp_path):
    pki = Pki.init(tmp_path, NOW_NS)
    issued = {name: pki.issue(name, role, NOW_NS, keys=k) for name, role, k in [
        ("rsu1", "rsu", None), ("two", "rsu", ("v2x/rsu/a/**", "v2x/rsu/b/objects", "v2x/rsu/a/time")),
        ("any", "rsu", ("v2x/rsu/*/**",)), ("time-only", "rsu", ("v2x/rsu/c/time",)), ("ego", "vehicle", None)]}
    ids = {name: certified_rsu_ids(read_cert(tmp_path / f"{name}.cert")) for name in issued}
    assert ids == {"rsu1": ("rsu1",), "two": ("a", "b"), "any": (), "time-only": (), "ego": ()}


def test_revoked_certificates_certify_nothing_and_the_first_file_names_an_rsu(tmp_path):
    directory = write_site(tmp_path, NOW_NS, rsu_ids=["rsu1", "rsu-nw"], vehicle_ids=["ego"])
    prepare_attacker_pki(directory, NOW_NS, "rsu1")  # rsu-evil; rsu1-revoked covers rsu1's keys, revoked
    assert certified_rsus(directory) == {"rsu-evil": directory / "rsu-evil.cert", "rsu-nw": directory / "rsu-nw.cert",
                                         "rsu1": directory / "rsu1.cert"}
    Pki.load(directory).revoke("rsu1", NOW_NS)
    assert list(certified_rsus(directory)) == ["rsu-evil", "rsu-nw"]


def test_a_certificate_of_another_ca_certifies_nothing(tmp_path, readme_pki):
    other = write_site(tmp_path / "other", NOW_NS, rsu_ids=["rsu9"])
    (readme_pki / "rsu9.cert").write_bytes((other / "rsu9.cert").read_bytes())
    assert list(certified_rsus(readme_pki)) == ["rsu1"]


def test_a_bad_certificate_is_one_error_naming_the_file(readme_pki):
    (readme_pki / "rsu2.cert").write_bytes(b"not a certificate")
    with pytest.raises(ValueError, match=r"rsu2\.cert: corrupt certificate"):
        obu_from_cli("--pki", str(readme_pki)).registered_rsus(site(("rsu-nw", NW)))


# --- what is left out, and said at start ----------------------------------------------------------

def test_the_obu_warns_of_each_certified_rsu_it_does_not_register(readme_pki):
    two = site(("rsu-nw", NW), ("rsu-se", SE))  # a multi-RSU site that does not list rsu1
    config = obu_from_cli("--pki", str(readme_pki))
    rsus = config.registered_rsus(two)
    assert rsus == {"rsu-nw": NW, "rsu-se": SE}
    lines = cli.registration_lines(config, rsus)
    assert lines[1:] == [f"WARNING: {readme_pki / 'rsu1.cert'}: RSU 'rsu1' holds a site certificate but is not "
                         "registered (registered: rsu-nw, rsu-se): it gets no intake priority and no reserved slot; "
                         "register it with --known-rsus (or a site that lists it)"]
    chosen = obu_from_cli("--pki", str(readme_pki), "--known-rsus", "rsu1")
    assert cli.registration_lines(chosen, chosen.registered_rsus(site(("rsu-nw", NW))))[1:] == []
    assert "from --known-rsus" in cli.registration_lines(chosen, {"rsu1": NW})[0]


def test_certified_rsus_are_registered_while_slots_are_left():
    certified = {f"r{i:02d}": None for i in range(70)}
    config = ObuConfig(max_unknown_rsus=16)
    rsus = config.registration(site(("rsu-nw", NW)), certified)
    assert len(rsus) == MAX_RSUS - 16 and list(rsus)[:2] == ["rsu-nw", "r00"]
    ObuPipeline(config.model_copy(update={"known_rsus": rsus}).pipeline_config(site(("rsu-nw", NW))))  # fits
    assert len(ObuConfig(v2v=True, max_peers=8).registration(site(("rsu-nw", NW)), certified)) == MAX_RSUS - 24
    assert len(ObuConfig(accept_unknown_rsus=False).registration(site(("rsu-nw", NW)), certified)) == 62
    left_out = unregistered_warnings(certified, rsus)
    assert len(left_out) == 70 - (MAX_RSUS - 17) and "'r69'" in left_out[-1]
