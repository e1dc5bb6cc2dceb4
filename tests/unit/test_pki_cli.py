"""``v2i pki``: init / issue / revoke / list / site / attacker / tls round trips on a temporary directory, and
every error as one line on stderr with exit code 2."""

from __future__ import annotations

import argparse
import json
import os
import stat

import pytest

from v2i.adversary.attack import configure_parser as attack_parser
from v2i.security.attacker_keys import load_attacker_keys
from v2i.security.envelope import Signer, Verifier
from v2i.security.pki import load_signer, load_trust
from v2i.cli import main


def pki(capsys, *argv: str) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``v2i pki ARGV``."""
    try:
        code = main(["pki", *argv])
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def listing(capsys, directory) -> dict[str, dict]:
    code, out, _ = pki(capsys, "list", str(directory), "--json")
    assert code == 0
    return {row["file"]: row for row in json.loads(out)["certificates"]}


def test_init_issue_revoke_list_round_trip(tmp_path, capsys):
    d = tmp_path / "site"
    assert pki(capsys, "init", str(d), "--days", "10", "--algorithm", "ed25519")[0] == 0
    code, out, _ = pki(capsys, "issue", str(d), "rsu7", "--role", "rsu", "--days", "2")
    assert code == 0 and "v2x/rsu/rsu7/**" in out and "ed25519" in out  # the CA's algorithm by default
    assert pki(capsys, "issue", str(d), "op", "--role", "operator", "--keys", "v2x/link/l1/control",
               "--algorithm", "p256")[0] == 0
    assert stat.S_IMODE(os.stat(d / "rsu7.key").st_mode) == 0o600
    rows = listing(capsys, d)
    assert list(rows) == ["ca", "op", "rsu7"]
    assert rows["op"]["keys"] == ["v2x/link/l1/control"] and rows["op"]["role"] == "operator"
    assert rows["op"]["algorithm"] == "p256" and rows["rsu7"]["algorithm"] == "ed25519"
    assert rows["rsu7"]["digest"] == load_signer(d, "rsu7").cert.digest.hex()
    assert not any(r["revoked"] for r in rows.values()) and all(r["valid_now"] for r in rows.values())
    code, out, _ = pki(capsys, "revoke", str(d), "rsu7")
    assert code == 0 and rows["rsu7"]["digest"] in out
    rows = listing(capsys, d)
    assert rows["rsu7"]["revoked"] and not rows["op"]["revoked"]
    assert load_trust(d).revoked == {bytes.fromhex(rows["rsu7"]["digest"])}
    code, out, _ = pki(capsys, "list", str(d))  # the table
    assert code == 0 and out.splitlines()[0].split()[:2] == ["subject", "role"]
    assert [line.split()[5] for line in out.splitlines()[1:]] == ["no", "no", "yes"]


def test_replace_reissues_with_a_new_key(tmp_path, capsys):
    d = tmp_path / "site"
    pki(capsys, "init", str(d))
    pki(capsys, "issue", str(d), "car", "--role", "vehicle")
    first = listing(capsys, d)["car"]["digest"]
    code, _, err = pki(capsys, "issue", str(d), "car", "--role", "vehicle")
    assert code == 2 and "already has a certificate" in err
    assert pki(capsys, "issue", str(d), "car", "--role", "vehicle", "--replace")[0] == 0
    assert listing(capsys, d)["car"]["digest"] != first


def test_site_is_idempotent_and_refuses_a_subject_under_another_role(tmp_path, capsys):
    d = tmp_path / "site"
    code, out, _ = pki(capsys, "site", str(d), "--rsu", "rsu1", "rsu2", "--vehicle", "ego")
    assert code == 0 and out.count("new") == 5  # ca, ego, operator, rsu1, rsu2
    before = listing(capsys, d)
    assert {r["role"] for r in before.values()} == {"ca", "rsu", "vehicle", "operator"}
    assert before["operator"]["keys"] == ["v2x/link/*/control"]
    code, out, _ = pki(capsys, "site", str(d), "--rsu", "rsu1", "rsu3", "--vehicle", "ego")
    assert code == 0 and out.count("new") == 1 and "new   rsu3" in out
    after = listing(capsys, d)
    assert all(after[k]["digest"] == before[k]["digest"] for k in before)
    code, _, err = pki(capsys, "site", str(d), "--rsu", "ego")
    assert code == 2 and "'ego' already holds a vehicle certificate, asked for as rsu" in err


def test_tls_writes_x509_in_a_directory_of_its_own(tmp_path, capsys):
    code, out, _ = pki(capsys, "tls", str(tmp_path / "tls"), "link", "rsu@127.0.0.1")
    assert code == 0 and {"tls-ca.pem", "link.pem", "link.key", "rsu.pem"} <= {p.name for p in (tmp_path / "tls").iterdir()}
    assert out.count("wrote") == 6
    pki(capsys, "init", str(tmp_path / "signing"))
    code, _, err = pki(capsys, "tls", str(tmp_path / "signing"), "link")
    assert code == 2 and "holds a signing PKI" in err


@pytest.mark.parametrize("argv, message", [
    (["issue", "{d}", "rsu1", "--role", "rsu"], "missing certificate"),
    (["revoke", "{d}", "rsu1"], "missing certificate"),
    (["list", "{d}/nowhere"], "no such directory"),
    (["issue", "{d}", "rsu1", "--role", "ca"], "invalid choice"),
    (["issue", "{d}", "rsu 1", "--role", "rsu"], "invalid subject"),
    (["issue", "{d}", "rsu1", "--role", "rsu", "--keys", "v2x//x"], "invalid key expression"),
    (["init", "{d}", "--days", "0"], "must be > 0"),
    (["tls", "{d}/tls", "bad_name!"], "must be a DNS name"),
])
def test_errors_are_one_line_and_exit_2(tmp_path, capsys, argv, message):
    if "invalid subject" in message:
        pki(capsys, "init", str(tmp_path))
    code, out, err = pki(capsys, *(a.format(d=tmp_path) for a in argv))
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1 and not out


def test_a_corrupt_or_second_ca_is_refused(tmp_path, capsys):
    d = tmp_path / "site"
    pki(capsys, "site", str(d), "--rsu", "rsu1")
    code, _, err = pki(capsys, "init", str(d))
    assert code == 2 and "already holds a CA" in err
    (d / "revoked.crl").write_bytes(b"\x00garbage")
    code, _, err = pki(capsys, "list", str(d))
    assert code == 2 and "revoked.crl" in err and len(err.strip().splitlines()) == 1
    (d / "revoked.crl").unlink()
    (d / "ca.cert").write_bytes(b"not a certificate")
    code, _, err = pki(capsys, "revoke", str(d), "rsu1")
    assert code == 2 and "ca.cert: corrupt certificate" in err


def test_attacker_adds_to_a_site_what_v2i_attack_reads(tmp_path, capsys):
    d = tmp_path / "site"
    code, _, err = pki(capsys, "attacker", str(d))
    assert code == 2 and "no site CA" in err and f"v2i pki site {d}" in err and not d.exists()
    assert pki(capsys, "site", str(d), "--rsu", "rsu1", "--vehicle", "ego")[0] == 0
    code, out, _ = pki(capsys, "attacker", str(d))
    lines = out.splitlines()
    assert code == 0 and [line.split()[:2] for line in lines[:3]] == [
        ["new", "rsu-evil.key/.cert:"], ["new", "stolen-vehicle.key/.cert:"], ["new", "rsu1-revoked.key/.cert:"]]
    assert "revoked in revoked.crl" in lines[2] and lines[-1].startswith(f"next: v2i attack --pki {d} --rsu-id rsu1")
    rows = listing(capsys, d)
    assert [r for r, row in rows.items() if row["revoked"]] == ["rsu1-revoked"]
    assert rows["rsu1-revoked"]["keys"] == ["v2x/rsu/rsu1/**"] and rows["rsu-evil"]["role"] == "rsu"
    assert rows["stolen-vehicle"]["role"] == "vehicle"
    attacker = load_attacker_keys(d, "rsu1")  # what v2i attack loads, with its defaults
    assert [i.cert.subject for i in attacker.stolen] == ["rsu-evil", "stolen-vehicle"]
    verifier, key = Verifier(load_trust(d), "strict", roles=("rsu",)), "v2x/rsu/rsu1/objects"
    t_ns = attacker.revoked.cert.valid_from_ns + 10**9
    assert verifier.verify(Signer(attacker.revoked).sign(b"ghost", t_ns, key), key, t_ns)[1] == "revoked"
    assert verifier.verify(Signer(attacker.stolen[0]).sign(b"ghost", t_ns, key), key, t_ns)[1] == "wrong_key"
    crl = (d / "revoked.crl").read_bytes()
    code, out, _ = pki(capsys, "attacker", str(d))  # again: everything kept, the list not re-signed
    assert code == 0 and [line.split()[0] for line in out.splitlines()[:3]] == ["kept"] * 3
    assert listing(capsys, d) == rows and (d / "revoked.crl").read_bytes() == crl
    code, out, _ = pki(capsys, "attacker", str(d), "--rsu-id", "rsu9", "--stolen-rsu", "rx", "--stolen-vehicle", "vx")
    assert code == 0 and "--rsu-id rsu9 --stolen rx,vx" in out
    assert load_attacker_keys(d, "rsu9", ("rx", "vx")).revoked.cert.digest in load_trust(d).revoked
    assert load_trust(d).revoked >= {bytes.fromhex(rows["rsu1-revoked"]["digest"])}
    attack = argparse.ArgumentParser()
    attack_parser(attack)
    assert "v2i pki attacker DIR --rsu-id RSU_ID" in " ".join(attack.format_help().split())


def test_attack_without_the_attackers_keys_says_how_to_make_them(tmp_path, capsys):
    d = tmp_path / "site"
    pki(capsys, "site", str(d), "--rsu", "rsu1", "--vehicle", "ego")
    code = main(["attack", "--connect", "tcp/127.0.0.1:9", "--sniff", "tcp/127.0.0.1:9", "--pki", str(d),
                 "--kinds", "unsigned", "--rsu-id", "rsu1", "--stolen", "thief"])
    err = capsys.readouterr().err
    assert code == 2 and "thief.cert: missing certificate" in err
    assert f"make the attacker's keys with: v2i pki attacker {d} --rsu-id rsu1 --stolen-rsu thief" in err
