"""Authenticated link control (issue 14 §3) without Zenoh: an emulator with ``pki`` applies only
fresh, unreplayed control signed by an operator certificate of its CA; every other control is
rejected with its reason counted in the stats; without ``pki`` every control is refused unless
``insecure_control``."""

from __future__ import annotations

import time

import msgpack
import numpy as np
import pytest
from pydantic import ValidationError

from link_emulator.config import LinkConfig
from link_emulator.control_auth import ControlAuth, sign_control
from link_emulator.relay import LinkRelay
from link_emulator.v2v_relay import V2vRelay
from schemas.codec import encode
from schemas.messages import LinkControl
from v2i.security.envelope import MAGIC, PREFIX
from v2i.security.pki import NS_PER_DAY, Pki, PkiError, load_signer
from v2i.security.site import write_site
from v2i.sim.clock import SystemClock
from v2i.cli import main

EP = ["tcp/127.0.0.1:1"]
S = 1_000_000_000
T0 = time.time_ns()  # certificates are issued at T0; controls are received at T0 + a few s


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """CA, operator, rsu1 (default keys), rogue (an RSU certificate with control keys), old (an
    operator expired a day ago), gone (a revoked operator); other (an operator of another CA)."""
    d = tmp_path_factory.mktemp("pki")
    write_site(d, T0, rsu_ids=["rsu1"], operators=["operator", "gone"])
    pki = Pki.load(d)
    pki.issue("rogue", "rsu", T0, keys=("v2x/link/*/control",))
    pki.issue("old", "operator", T0 - 3 * NS_PER_DAY, days=1)
    pki.revoke("gone", T0)
    other = tmp_path_factory.mktemp("other")
    write_site(other, T0, operators=["operator"])
    return {"dir": d, "other": other}


def relay(pki=None, **fields) -> LinkRelay:
    config = LinkConfig(link_id="l1", rsu_connect=EP, vehicle_connect=EP, profile="ideal",
                        pki=None if pki is None else str(pki), **fields)
    return LinkRelay(config, SystemClock())


def signed(site, subject="operator", at_ns=T0 + S, seq=1, directory=None, link_id="l1") -> bytes:
    identity = load_signer(directory or site["dir"], subject)
    return sign_control(LinkControl(link_id=link_id, seq=seq, outage=True, duration_s=5.0), identity, at_ns)


def control(r: LinkRelay) -> dict:
    return r.stats_snapshot(0)["control"]


def test_signed_operator_control_is_applied(site):
    r = relay(site["dir"])
    r._control_arrival(signed(site, seq=7), T0 + S + 20_000_000)  # received 20 ms after signing
    assert control(r)["applied"] == 1 and control(r)["rejected"] == {}
    assert control(r)["recent"][-1]["seq"] == 7
    assert r.pairs[0].model.downlink.transmit(T0 + 2 * S, 100) is None  # inside the 5 s outage


@pytest.mark.parametrize("make, received_ns, reason", [
    (lambda site: encode(LinkControl(link_id="l1", seq=1, clear=True)), T0 + S, "unsigned"),
    (lambda site: signed(site)[:-1] + bytes([signed(site)[-1] ^ 1]), T0 + S, "bad_signature"),  # forged
    (lambda site: signed(site, link_id="l2").replace(b"l2", b"l1"), T0 + S, "bad_signature"),  # moved to l1
    (lambda site: signed(site, directory=site["other"]), T0 + S, "unknown_cert"),
    (lambda site: signed(site, "rsu1"), T0 + S, "wrong_role"),  # an RSU's certificate, its own keys
    (lambda site: signed(site, "rogue"), T0 + S, "wrong_role"),
    (lambda site: signed(site, "gone"), T0 + S, "revoked"),
    (lambda site: signed(site, "old"), T0 + S, "expired"),
    (lambda site: signed(site), T0 + S + 2 * S + 1, "stale"),  # 2 s after signing, plus 1 ns
    (lambda site: signed(site), T0 + S - S // 2 - 1, "future"),  # signed 0.5 s + 1 ns ahead
    (lambda site: PREFIX + b"\x00" * 40, T0 + S, "malformed"),
    (lambda site: msgpack.packb([MAGIC, b"x", b"y" * 8, -1, b"z" * 64]), T0 + S, "malformed"),
])
def test_every_bad_control_is_rejected_with_its_reason_and_changes_nothing(site, make, received_ns, reason):
    r = relay(site["dir"])
    r._control_arrival(make(site), received_ns)
    assert control(r)["applied"] == 0 and control(r)["rejected"] == {reason: 1}
    assert r.pairs[0].model.downlink.transmit(T0 + 2 * S, 100) is not None  # no outage
    if reason != "malformed":  # the seq it claims is reported, so its sender learns why
        assert control(r)["recent"][-1]["seq"] == 1


def test_the_window_edges_are_accepted(site):
    r = relay(site["dir"])
    r._control_arrival(signed(site, seq=1), T0 + 3 * S)  # exactly 2 s old
    r._control_arrival(signed(site, seq=2, at_ns=T0 + 4 * S), T0 + 4 * S - S // 2)  # exactly 0.5 s ahead
    assert control(r)["applied"] == 2


def test_a_replayed_control_is_rejected(site):
    r = relay(site["dir"])
    message = signed(site)
    r._control_arrival(message, T0 + S + 1000)
    r._control_arrival(message, T0 + S + 500_000_000)
    assert control(r)["applied"] == 1 and control(r)["rejected"] == {"replayed": 1}


def test_the_window_is_configurable(site):
    r = relay(site["dir"], control_max_age_s=10.0, control_max_ahead_s=0.0)
    r._control_arrival(signed(site, seq=1), T0 + 6 * S)
    r._control_arrival(signed(site, seq=2, at_ns=T0 + 7 * S), T0 + 7 * S - 1)
    assert control(r)["applied"] == 1 and control(r)["rejected"] == {"future": 1}


def test_a_revocation_written_while_running_applies_to_the_next_control(tmp_path):
    write_site(tmp_path, T0, operators=["operator", "op2"])
    r = relay(tmp_path)
    r._control_arrival(sign_control(LinkControl(link_id="l1", seq=1, clear=True), load_signer(tmp_path, "op2"),
                                    T0 + S), T0 + S)
    Pki.load(tmp_path).revoke("op2", T0 + S)
    r._control_arrival(sign_control(LinkControl(link_id="l1", seq=2, clear=True), load_signer(tmp_path, "op2"),
                                    T0 + 3 * S), T0 + 3 * S)  # the list is re-read at most once a second
    r._control_arrival(signed({"dir": tmp_path}, seq=3, at_ns=T0 + 3 * S), T0 + 3 * S)
    assert control(r)["applied"] == 2 and control(r)["rejected"] == {"revoked": 1}


def test_without_pki_every_control_is_refused_as_unauthenticated(site):
    r = relay()
    r._control_arrival(encode(LinkControl(link_id="l1", seq=4, clear=True)), T0)
    r._control_arrival(signed(site), T0 + S)
    c = control(r)
    assert c["applied"] == 0 and c["rejected"] == {"unauthenticated": 2}
    assert c["recent"][0]["seq"] == 4 and "without --pki" in c["recent"][0]["error"]
    assert "refused" in r.control_auth.describe()


def test_insecure_control_accepts_unsigned_and_unwraps_signed_unchecked(site):
    r = relay(insecure_control=True)
    r._control_arrival(encode(LinkControl(link_id="l1", seq=1, clear=True)), T0)
    r._control_arrival(signed(site, "rsu1", seq=2), T0 + 100 * S)  # any signer, any time: unchecked
    assert control(r)["applied"] == 2 and "NOT authenticated" in r.control_auth.describe()


def test_the_v2v_emulator_authenticates_the_same_way(site):
    vehicles = [{"vehicle_id": v, "connect": EP} for v in ("car1", "car2")]
    r = V2vRelay(LinkConfig(link_id="l1", v2v=True, vehicles=vehicles, profile="ideal", pki=str(site["dir"])),
                 SystemClock())
    r._control_arrival(encode(LinkControl(link_id="l1", seq=1, clear=True)), T0 + S)
    r._control_arrival(signed(site, seq=2), T0 + S)
    c = r.stats_snapshot(T0)["control"]
    assert c["applied"] == 1 and c["rejected"] == {"unsigned": 1}
    unauth = V2vRelay(LinkConfig(link_id="l1", v2v=True, vehicles=vehicles, profile="ideal"), SystemClock())
    unauth._control_arrival(signed(site, seq=3), T0 + S)
    assert unauth.stats_snapshot(T0)["control"]["rejected"] == {"unauthenticated": 1}


def test_hostile_bytes_never_raise(site):
    """Random bytes, random bytes behind the envelope prefix, and bit flips of a genuine control."""
    rng = np.random.default_rng(0)
    auth = ControlAuth.create("l1", str(site["dir"]), insecure=False)
    genuine = signed(site)
    reasons = set()
    for i in range(3000):
        if i % 3 == 0:
            data = rng.bytes(int(rng.integers(0, 300)))
        elif i % 3 == 1:
            data = PREFIX + rng.bytes(int(rng.integers(0, 400)))
        else:
            flipped = bytearray(genuine)
            flipped[int(rng.integers(len(flipped)))] ^= 1 << int(rng.integers(8))
            data = bytes(flipped)
        opened = auth.open(data, T0 + S)
        assert opened.payload is None
        reasons.add(opened.reason)
    assert {"unsigned", "malformed", "bad_signature"} <= reasons


def test_config_and_command_line_errors(site, tmp_path, capsys):
    with pytest.raises(ValidationError, match="not both"):
        LinkConfig(rsu_connect=EP, vehicle_connect=EP, pki=str(site["dir"]), insecure_control=True)
    with pytest.raises(PkiError, match="ca.cert: missing certificate"):
        relay(tmp_path)
    assert main(["link", "--rsu-connect", EP[0], "--vehicle-connect", EP[0], "--pki", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "ca.cert: missing certificate" in err and len(err.strip().splitlines()) == 1
    code = main(["link", "set", "--connect", EP[0], "--pki", str(site["dir"]), "--identity", "rsu1", "--clear"])
    assert code == 2 and "link control needs an operator's" in capsys.readouterr().err
