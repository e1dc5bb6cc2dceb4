"""v2i.security.site: a whole site's PKI in one call, idempotent, and its in-memory twin."""

import pytest

from v2i.security.envelope import Signer, Verifier
from v2i.security.pki import Pki, load_trust
from v2i.security.site import memory_site, write_site

NOW_NS = 1_800_000_000 * 10**9


def test_write_site_issues_every_subject_once(tmp_path):
    write_site(tmp_path, NOW_NS, ["rsu1", "rsu2"], ["ego"])
    first = (tmp_path / "rsu1.cert").read_bytes()
    write_site(tmp_path, NOW_NS + 10**9, ["rsu1", "rsu3"], ["ego"])  # keeps rsu1, adds rsu3
    assert (tmp_path / "rsu1.cert").read_bytes() == first
    subjects = {p.stem for p in tmp_path.glob("*.cert")}
    assert subjects == {"ca", "rsu1", "rsu2", "rsu3", "ego", "operator"}
    assert len(load_trust(tmp_path).known) == 5


def test_write_site_keeps_an_existing_ca_and_its_revocations(tmp_path):
    write_site(tmp_path, NOW_NS, ["rsu1"])
    Pki.load(tmp_path).revoke("rsu1", NOW_NS)
    write_site(tmp_path, NOW_NS, ["rsu1", "rsu2"])
    trust = load_trust(tmp_path)
    assert len(trust.revoked) == 1


def test_one_id_under_two_roles_is_refused(tmp_path):
    with pytest.raises(ValueError, match="both rsu and vehicle"):
        write_site(tmp_path, NOW_NS, ["x"], ["x"])


def test_memory_site_signs_and_verifies_by_role_keys():
    trust, ids = memory_site(NOW_NS, ["rsu1"], ["ego"])
    verifier = Verifier(trust, "strict")
    rsu = Signer(ids["rsu1"])
    data = rsu.sign(b"list", NOW_NS, "v2x/rsu/rsu1/objects")
    assert verifier.verify(data, "v2x/rsu/rsu1/objects", NOW_NS) == (b"list", "ok")
    vehicle = Signer(ids["ego"]).sign(b"ghost", NOW_NS, "v2x/rsu/rsu1/objects")
    assert verifier.verify(vehicle, "v2x/rsu/rsu1/objects", NOW_NS) == (None, "wrong_key")
