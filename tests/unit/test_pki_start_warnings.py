"""What a service says loudly at start about its PKI folder (issue 32, item 5)."""

import os

from v2i.security.pki import Pki, start_warnings

S = 10**9
NOW = 1_767_225_600 * S
DAY = 86_400 * S


def site(tmp_path, days: float = 365):
    pki = Pki.init(tmp_path / "pki", NOW - DAY, days=3650)
    pki.issue("rsu1", "rsu", NOW - DAY, days=days)
    return pki, tmp_path / "pki"


def test_a_good_site_says_nothing(tmp_path):
    _, folder = site(tmp_path)
    assert start_warnings(folder, NOW, own="rsu1") == []


def test_world_readable_keys_are_named(tmp_path):
    _, folder = site(tmp_path)
    os.chmod(folder / "ca.key", 0o644)
    [line] = start_warnings(folder, NOW)
    assert "ca.key" in line and "0644" in line and "chmod 600" in line and "off service hosts" in line


def test_an_expired_or_revoked_own_certificate_is_said(tmp_path):
    pki, folder = site(tmp_path, days=0.5)  # issued a day ago for half a day
    [line] = start_warnings(folder, NOW, own="rsu1")
    assert "rsu1.cert" in line and "expired" in line and "drop" in line
    assert "not yet valid" in start_warnings(folder, NOW - 2 * DAY, own="rsu1")[0]
    pki.revoke("rsu1", NOW - DAY * 9 // 10)
    lines = start_warnings(folder, NOW - DAY * 3 // 4, own="rsu1")  # in date, but revoked
    assert len(lines) == 1 and "revoked" in lines[0]
