"""v2i.security.tls (X.509 material for Zenoh mTLS) and the site Zenoh config merged by v2i.runtime.transport."""

from __future__ import annotations

import ipaddress
import json
import stat
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from schemas.codec import MAX_MESSAGE_BYTES
from v2i.runtime.transport import CONFIG_FILE_ENV, TLS_DIR_ENV, load_config_file, session_config
from v2i.security.pki import Pki, PkiError
from v2i.security.tls import issue_tls, parse_name

NOW_NS = 1_790_000_000 * 10**9
DEPLOY = Path(__file__).resolve().parents[2] / "deploy" / "zenoh"


def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_issue_writes_a_ca_and_server_client_certificates(tmp_path: Path) -> None:
    written = issue_tls(tmp_path, ["rsu@10.10.1.1,fd00::1", "operator"], NOW_NS, days=2.0)
    assert [p.name for p in written] == ["tls-ca.pem", "tls-ca.key", "rsu.pem", "rsu.key", "operator.pem", "operator.key"]
    for key in ("tls-ca.key", "rsu.key", "operator.key"):
        assert stat.S_IMODE((tmp_path / key).stat().st_mode) == 0o600
    ca, rsu = _cert(tmp_path / "tls-ca.pem"), _cert(tmp_path / "rsu.pem")
    rsu.verify_directly_issued_by(ca)
    assert rsu.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "rsu"
    san = rsu.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.DNSName) == ["rsu"]
    assert san.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("10.10.1.1"), ipaddress.ip_address("fd00::1")]
    eku = rsu.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert set(eku) == {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH}
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    lifetime_s = (rsu.not_valid_after_utc - rsu.not_valid_before_utc).total_seconds()
    assert lifetime_s == pytest.approx(2 * 86_400 + 300)  # 2 days, back-dated 5 min
    assert rsu.not_valid_after_utc.timestamp() == pytest.approx(NOW_NS / 1e9 + 2 * 86_400)


def test_the_ca_is_kept_and_names_are_reissued(tmp_path: Path) -> None:
    issue_tls(tmp_path, ["obu"], NOW_NS)
    ca_pem, obu_pem = (tmp_path / "tls-ca.pem").read_bytes(), (tmp_path / "obu.pem").read_bytes()
    assert [p.name for p in issue_tls(tmp_path, ["obu"], NOW_NS)] == ["obu.pem", "obu.key"]
    assert (tmp_path / "tls-ca.pem").read_bytes() == ca_pem and (tmp_path / "obu.pem").read_bytes() != obu_pem
    _cert(tmp_path / "obu.pem").verify_directly_issued_by(_cert(tmp_path / "tls-ca.pem"))


@pytest.mark.parametrize("name", ["", "-rsu", "rsu/..", "tls-ca", "a b", "rsu@", "rsu@10.0.0.300", "rsu@host"])
def test_bad_names_are_refused(name: str) -> None:
    with pytest.raises(ValueError):
        parse_name(name)


def test_bad_ca_files_are_named(tmp_path: Path) -> None:
    issue_tls(tmp_path, [], NOW_NS)
    (tmp_path / "tls-ca.key").chmod(0o644)
    with pytest.raises(PkiError, match="tls-ca.key: private key is accessible by others"):
        issue_tls(tmp_path, ["obu"], NOW_NS)
    (tmp_path / "tls-ca.key").chmod(0o600)
    (tmp_path / "tls-ca.key").write_bytes(b"not a key")
    with pytest.raises(PkiError, match="tls-ca.key: corrupt private key"):
        issue_tls(tmp_path, ["obu"], NOW_NS)
    (tmp_path / "tls-ca.key").unlink()
    with pytest.raises(PkiError, match="tls-ca.key: missing"):
        issue_tls(tmp_path, ["obu"], NOW_NS)


def test_a_signing_pki_directory_is_refused(tmp_path: Path) -> None:
    Pki.init(tmp_path, NOW_NS)
    with pytest.raises(PkiError, match="ca.cert: .* holds a signing PKI"):
        issue_tls(tmp_path, ["rsu"], NOW_NS)


@pytest.mark.parametrize("role", ["rsu", "link", "obu", "operator", "monitor"])
def test_shipped_configs_load_with_their_certificates(role: str, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv(TLS_DIR_ENV, str(tmp_path))
    with pytest.raises(ValueError, match=rf"{role}.json5: transport/link/tls/\w+ .*: no such file"):
        load_config_file(DEPLOY / f"{role}.json5")
    issue_tls(tmp_path, [role], NOW_NS)
    conf = load_config_file(DEPLOY / f"{role}.json5")
    assert json.loads(conf.get_json("transport/link/tls/listen_certificate")) == str(tmp_path / f"{role}.pem")
    assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is True
    acl = json.loads(conf.get_json("access_control"))
    assert acl["enabled"] and acl["default_permission"] == "deny"


def test_site_config_is_the_base_and_the_safety_settings_win(tmp_path: Path, monkeypatch) -> None:
    site = tmp_path / "site.json5"
    site.write_text(json.dumps({
        "mode": "client", "listen": {"endpoints": ["tcp/0.0.0.0:1"]},
        "scouting": {"multicast": {"enabled": True}, "gossip": {"enabled": True}},
        "transport": {"shared_memory": {"enabled": True}, "link": {"rx": {"max_message_size": 10**9}}},
        "queries_default_timeout": 1234}))
    monkeypatch.delenv("V2I_ZENOH_MODE", raising=False)
    monkeypatch.setenv(CONFIG_FILE_ENV, str(site))
    conf = session_config(listen=["tls/127.0.0.1:7447"])
    value = lambda key: json.loads(conf.get_json(key))  # noqa: E731
    assert value("queries_default_timeout") == 1234  # the file's own setting
    assert value("mode") == "client"  # the file's mode when neither the argument nor $V2I_ZENOH_MODE say
    assert value("listen/endpoints") == ["tls/127.0.0.1:7447"] and value("connect/endpoints") == []
    assert not value("scouting/multicast/enabled") and not value("scouting/gossip/enabled")
    assert not value("transport/shared_memory/enabled")
    assert value("transport/link/rx/max_message_size") == MAX_MESSAGE_BYTES
    assert json.loads(session_config(mode="peer").get_json("mode")) == "peer"
    monkeypatch.setenv("V2I_ZENOH_MODE", "peer")
    assert json.loads(session_config().get_json("mode")) == "peer"


def test_a_bad_site_config_is_named(tmp_path: Path, monkeypatch) -> None:
    bad = tmp_path / "bad.json5"
    bad.write_text("{mode: ")
    monkeypatch.setenv(CONFIG_FILE_ENV, str(bad))
    with pytest.raises(ValueError, match=rf"V2I_ZENOH_CONFIG: Zenoh config {bad}: "):
        session_config()
    monkeypatch.setenv(CONFIG_FILE_ENV, str(tmp_path / "absent.json5"))
    with pytest.raises(ValueError, match="absent.json5: no such file"):
        session_config()


def test_zenoh_config_flag_is_checked_before_the_command_runs(tmp_path: Path, capsys, monkeypatch) -> None:
    from v2i.cli import main

    monkeypatch.delenv(CONFIG_FILE_ENV, raising=False)
    assert main(["router", "--listen", "tcp/127.0.0.1:1", "--zenoh-config", str(tmp_path / "absent.json5")]) == 2
    assert "v2i router: Zenoh config" in capsys.readouterr().err and CONFIG_FILE_ENV not in __import__("os").environ
