"""Attack messages (v2i.adversary.attack_messages) against the verifier they are built to fool.

Each kind must be refused by ``v2i.security.envelope.Verifier`` under ``strict`` with the reason it
was built for; and the same bytes must carry an accepted ghost when nothing checks (``off``), or
the attack would not be an attack.
"""

from __future__ import annotations

import numpy as np
import pytest

from v2i.adversary.attack_messages import (ALL_KINDS, CONTROL_VARIANTS, FLOOD_VARIANTS, GHOST_AHEAD_M, GHOST_ID,
                                           HOSTILE_KINDS, INTENDED, JUNK_BYTES, KINDS, LIST_KINDS, RELAY_KINDS,
                                           TIME_SHIFT_NS, AttackMessages, ghost_xy, signer_digest)
from v2i.core.frames import Pose2D
from schemas import keys
from schemas.classes import ObjectClass
from schemas.codec import decode, encode
from schemas.messages import LinkControl, ObjectList, ObjectListHeader, TimeReply, TimeRequest
from v2i.security.attacker_keys import (STOLEN_RSU, STOLEN_VEHICLE, load_attacker_keys, prepare_attacker_pki,
                                    revoked_subject)
from v2i.security.envelope import PREFIX, Signer, Verifier, parse
from v2i.security.pki import Pki, PkiError, load_signer, load_trust
from v2i.security.site import write_site

NOW_NS = 1_800_000_000 * 10**9  # when the site was made
T_NS = NOW_NS + 10 * 10**9  # when the attack happens
RSU = "rsu1"
EGO = Pose2D(5.25, -12.35, np.pi / 2)


@pytest.fixture(scope="module")
def pki_dir(tmp_path_factory):
    directory = tmp_path_factory.mktemp("pki")
    prepare_attacker_pki(directory, NOW_NS, RSU)  # before the site: the harness's order
    write_site(directory, NOW_NS, rsu_ids=[RSU], vehicle_ids=["ego"])
    return directory


@pytest.fixture
def genuine(pki_dir):
    return Signer(load_signer(pki_dir, RSU))


def attack(pki_dir, genuine: Signer, seed: int = 0) -> AttackMessages:
    captured = genuine.sign(b"any", T_NS, keys.rsu_objects(RSU))
    return AttackMessages(RSU, load_attacker_keys(pki_dir, RSU), np.random.default_rng(seed),
                          genuine_digest=signer_digest(captured))


def genuine_list(genuine: Signer, t_ns: int, seq: int) -> bytes:
    header = ObjectListHeader(rsu_id=RSU, seq=seq, capture_time_ns=t_ns - 100_000_000, publish_time_ns=t_ns)
    return genuine.sign(encode(ObjectList(header=header)), t_ns, keys.rsu_objects(RSU))


def test_prepare_is_idempotent_and_revokes_only_the_former_key(pki_dir):
    before = {p.name: p.read_bytes() for p in pki_dir.glob("*.cert")}
    prepare_attacker_pki(pki_dir, T_NS + 10**9, RSU)
    assert {p.name: p.read_bytes() for p in pki_dir.glob("*.cert")} == before
    trust = load_trust(pki_dir)
    digests = {s: load_signer(pki_dir, s).cert.digest for s in (RSU, STOLEN_RSU, STOLEN_VEHICLE, revoked_subject(RSU))}
    assert trust.revoked == {digests[revoked_subject(RSU)]}
    assert load_signer(pki_dir, revoked_subject(RSU)).cert.keys == (f"v2x/rsu/{RSU}/**",)
    with pytest.raises(PkiError, match="missing"):
        load_attacker_keys(pki_dir, RSU, stolen=("nobody",))


def test_ghost_is_a_pedestrian_ahead_of_the_ego(pki_dir, genuine):
    messages = attack(pki_dir, genuine)
    _, data = messages.list_message("unsigned", T_NS, EGO)
    ghost = decode(data, ObjectList)
    assert ghost.header.rsu_id == RSU and ghost.header.publish_time_ns == T_NS
    (obj,) = list(ghost.objects)
    assert obj.cls == ObjectClass.PEDESTRIAN and obj.id == GHOST_ID
    assert np.hypot(obj.x - EGO.x, obj.y - EGO.y) == pytest.approx(GHOST_AHEAD_M, abs=0.02)
    np.testing.assert_allclose(ghost_xy(Pose2D(0.0, 0.0, 0.0)), [GHOST_AHEAD_M, 0.0])


@pytest.mark.parametrize("kind", LIST_KINDS)
def test_each_list_kind_is_rejected_for_its_reason_and_would_be_a_ghost_unchecked(pki_dir, genuine, kind):
    trust = load_trust(pki_dir)
    strict, off = Verifier(trust, "strict", roles=("rsu",)), Verifier(trust, "off")  # roles: as the OBU
    messages = attack(pki_dir, genuine)
    captured = genuine_list(genuine, T_NS - 500_000_000, seq=7)
    assert strict.verify(captured, keys.rsu_objects(RSU), T_NS)[1] == "ok"  # the OBU got the original first
    key_expr, data = messages.list_message(kind, T_NS, EGO, captured=captured)
    assert key_expr == keys.rsu_objects(RSU)
    payload, reason = strict.verify(data, key_expr, T_NS)
    assert payload is None and reason == INTENDED[kind][0]  # the first: rsu-evil's key for wrong_key
    opened, unchecked = off.verify(data, key_expr, T_NS)
    assert unchecked == "unchecked"
    objects = list(decode(opened, ObjectList).objects)
    expected = [] if kind == "replayed" else [ObjectClass.PEDESTRIAN]  # a replay carries the genuine list
    assert [o.cls for o in objects] == expected


def test_forged_uses_both_a_random_and_an_impostor_signature(pki_dir, genuine):
    messages = attack(pki_dir, genuine, seed=3)
    verifier = Verifier(load_trust(pki_dir), "strict")
    signatures = set()
    for i in range(20):
        _, data = messages.list_message("forged", T_NS + i, EGO)
        assert signer_digest(data) == genuine.digest
        assert verifier.verify(data, keys.rsu_objects(RSU), T_NS)[1] == "bad_signature"
        signatures.add(data[-64:])
    assert len(signatures) == 20
    with pytest.raises(ValueError, match="digest"):
        AttackMessages(RSU, load_attacker_keys(pki_dir, RSU), np.random.default_rng(0)).list_message(
            "forged", T_NS, EGO)


def test_revoked_key_passes_without_the_revocation_list(pki_dir, genuine, tmp_path):
    """The revoked kind is otherwise perfect: only the CRL stops it."""
    trust = load_trust(pki_dir)
    key_expr, data = attack(pki_dir, genuine).list_message("revoked", T_NS, EGO)
    unrevoked = Verifier(type(trust)(trust.ca, trust.ca_key, frozenset(), trust.known), "strict")
    payload, reason = unrevoked.verify(data, key_expr, T_NS)
    assert reason == "ok" and decode(payload, ObjectList).objects[0].cls == ObjectClass.PEDESTRIAN


def test_stolen_keys_are_genuine_on_their_own_keys(pki_dir, genuine):
    """wrong_key fails only on coverage: the stolen RSU's key is accepted on its own RSU's key."""
    verifier, obu = Verifier(load_trust(pki_dir), "strict"), Verifier(load_trust(pki_dir), "strict", roles=("rsu",))
    reasons, obu_reasons = set(), set()
    messages = attack(pki_dir, genuine)
    for _ in range(4):  # alternates between the stolen RSU and vehicle keys
        _, data = messages.list_message("wrong_key", T_NS, EGO)
        reasons.add(verifier.verify(data, keys.rsu_objects(RSU), T_NS)[1])
        obu_reasons.add(obu.verify(data, keys.rsu_objects(RSU), T_NS)[1])
        digest = signer_digest(data)
        assert digest in {load_signer(pki_dir, s).cert.digest for s in (STOLEN_RSU, STOLEN_VEHICLE)}
    assert reasons == {"wrong_key"} and obu_reasons == {"wrong_key", "wrong_role"}
    rogue = Signer(load_signer(pki_dir, STOLEN_RSU)).sign(b"x", T_NS, keys.rsu_objects(STOLEN_RSU))
    assert verifier.verify(rogue, keys.rsu_objects(STOLEN_RSU), T_NS)[1] == "ok"


def test_replay_older_than_the_window_is_stale(pki_dir, genuine):
    verifier = Verifier(load_trust(pki_dir), "strict", freshness_ns=2 * 10**9)
    captured = genuine_list(genuine, T_NS - 3 * 10**9, seq=1)
    assert verifier.verify(captured, keys.rsu_objects(RSU), T_NS - 3 * 10**9)[1] == "ok"
    _, data = attack(pki_dir, genuine).list_message("replayed", T_NS, EGO, captured=captured)
    assert verifier.verify(data, keys.rsu_objects(RSU), T_NS)[1] == "stale"
    with pytest.raises(ValueError, match="captured"):
        attack(pki_dir, genuine).list_message("replayed", T_NS, EGO)


@pytest.mark.parametrize("variant, reason", [("unsigned", "unsigned"), ("wrong_key", "wrong_key"),
                                             ("forged", "bad_signature")])
def test_forged_time_replies_shift_the_clock_and_are_rejected(pki_dir, genuine, variant, reason):
    request = TimeRequest(obu_id="ego", seq=42, t1_ns=T_NS)
    offset_ns = 250_000_000
    data = attack(pki_dir, genuine).time_reply(request, offset_ns, variant)
    strict, off = Verifier(load_trust(pki_dir), "strict"), Verifier(load_trust(pki_dir), "off")
    assert strict.verify(data, keys.rsu_time(RSU), None) == (None, reason)
    reply = decode(off.verify(data, keys.rsu_time(RSU), None)[0], TimeReply)
    assert (reply.seq, reply.t1_ns) == (request.seq, request.t1_ns)
    # NTP offset ((t2 - t1) + (t3 - t4)) / 2 with t4 = t1 + 1 ms: the forged shift, within 0.1 ms
    theta_ns = ((reply.t2_ns - reply.t1_ns) + (reply.t3_ns - (request.t1_ns + 1_000_000))) / 2
    assert theta_ns - offset_ns == pytest.approx(TIME_SHIFT_NS, abs=100_000)


@pytest.mark.parametrize("variant, reason", list(zip(CONTROL_VARIANTS, ("unsigned", "wrong_role"))))
def test_control_outage_is_unsigned_or_signed_by_a_non_operator(pki_dir, genuine, variant, reason):
    key_expr, data = attack(pki_dir, genuine).control(variant, seq=9, generation_ns=T_NS)
    assert key_expr == keys.link_control("link1")
    strict = Verifier(load_trust(pki_dir), "strict", roles=("operator",))  # as the link emulator
    assert strict.verify(data, key_expr, T_NS) == (None, reason)
    assert reason in INTENDED["control"]
    control = decode(Verifier(load_trust(pki_dir), "off").verify(data, key_expr, T_NS)[0], LinkControl)
    assert control.outage and control.duration_s == 3600.0 and control.seq == 9
    operator = Signer(load_signer(pki_dir, "operator")).sign(encode(control), T_NS, key_expr)
    assert strict.verify(operator, key_expr, T_NS)[1] == "ok"  # the same control from the operator passes


def test_prepare_on_an_empty_directory_makes_a_ca(tmp_path):
    prepare_attacker_pki(tmp_path, NOW_NS, "rsu-9")
    assert Pki.load(tmp_path).ca.cert.role == "ca"
    assert load_attacker_keys(tmp_path, "rsu-9").revoked.cert.subject == "rsu-9-revoked"


def test_flood_variants_are_refused_for_their_reasons_and_carry_a_ghost_unchecked(pki_dir, genuine):
    """Junk is unsigned or malformed, the rest a ghost list unsigned or forged on the genuine digest."""
    trust = load_trust(pki_dir)
    strict, off = Verifier(trust, "strict", roles=("rsu",)), Verifier(trust, "off")
    messages, key_expr = attack(pki_dir, genuine), keys.rsu_objects(RSU)
    reasons: dict[str, set[str]] = {v: set() for v in FLOOD_VARIANTS}
    for _ in range(40):
        for variant in FLOOD_VARIANTS:
            data = messages.flood(variant, T_NS, EGO)
            payload, reason = strict.verify(data, key_expr, T_NS)
            assert payload is None and reason in INTENDED["flood"]
            reasons[variant].add(reason)
            if variant != "junk":
                ghost = decode(off.verify(data, key_expr, T_NS)[0], ObjectList)
                assert [o.cls for o in ghost.objects] == [ObjectClass.PEDESTRIAN]
            else:
                assert JUNK_BYTES[0] <= len(data) <= JUNK_BYTES[1] + len(PREFIX)
    assert reasons == {"junk": {"unsigned", "malformed"}, "unsigned": {"unsigned"}, "forged": {"bad_signature"}}
    forged = messages.flood("forged", T_NS, EGO)
    assert signer_digest(forged) == genuine.digest and parse(forged).generation_ns == T_NS  # fresh: costs a verify


def test_flood_reuses_a_given_payload_and_refuses_unknown_variants(pki_dir, genuine):
    messages = attack(pki_dir, genuine)
    payload = messages.ghost_payload(T_NS, EGO)
    assert messages.flood("unsigned", T_NS, EGO, payload) == payload
    assert parse(messages.flood("forged", T_NS, EGO, payload)).payload == payload
    with pytest.raises(ValueError, match="unknown flood variant"):
        messages.flood("loud", T_NS, EGO)
    with pytest.raises(ValueError, match="digest"):
        AttackMessages(RSU, load_attacker_keys(pki_dir, RSU), np.random.default_rng(0)).flood("forged", T_NS, EGO)


def test_the_opt_in_kinds_are_not_in_the_default_list():
    assert not set(HOSTILE_KINDS) & set(KINDS) and ALL_KINDS == KINDS + HOSTILE_KINDS
    assert set(RELAY_KINDS) < set(HOSTILE_KINDS) and "flood" not in RELAY_KINDS
