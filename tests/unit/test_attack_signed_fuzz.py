"""Hostile signed envelopes of ``v2i fuzz --target obu-signed`` (v2i.adversary.fuzz_signed) against the
verifier and the decoder: counted reasons, never an exception; validly signed garbage passes the
verifier and is refused by the decoder."""

from __future__ import annotations

import numpy as np
import pytest

from v2i.adversary.fuzz_signed import FUZZ_RSUS, SIGNED_KINDS, SignedHostile
from v2i.adversary.hostile import HostileInputs
from schemas import keys
from schemas.codec import CodecError, decode
from schemas.messages import ObjectList, PredictionList
from v2i.security.envelope import REJECTIONS, Signer, Verifier
from v2i.security.pki import load_signer, load_trust
from v2i.security.site import write_site

NOW_NS = 1_800_000_000 * 10**9
EXPECTED = {
    "garbage_prefix": {"unsigned", "malformed"},
    "truncated": {"unsigned", "malformed"},
    "huge_fields": {"unsigned", "malformed", "unknown_cert", "bad_signature", "expired"},  # expired: time 2^64 - 1
    "bit_flips": set(REJECTIONS) | {"ok"},  # a flip in the msgpack framing may leave a valid envelope
    "signed_hostile": {"ok", "malformed"},  # malformed: an oversized payload makes the envelope too large
}


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    directory = tmp_path_factory.mktemp("pki")
    write_site(directory, NOW_NS - 10**9, rsu_ids=["rsu1", *FUZZ_RSUS])
    return load_trust(directory), {r: Signer(load_signer(directory, r)) for r in FUZZ_RSUS}


@pytest.mark.parametrize("kind", SIGNED_KINDS)
@pytest.mark.parametrize("type_name, model", [("object_list", ObjectList), ("prediction_list", PredictionList)])
def test_signed_kinds_reach_their_reasons_and_never_raise(site, kind, type_name, model):
    trust, signers = site
    rng = np.random.default_rng(7)
    hostile = SignedHostile(rng, HostileInputs(rng), signers)
    verifier = Verifier(trust, "strict")
    topic = keys.rsu_objects if type_name == "object_list" else keys.rsu_predictions
    reasons, decoded = set(), 0
    for i in range(40):
        rsu_id = FUZZ_RSUS[i % len(FUZZ_RSUS)]
        data = hostile.make(kind, type_name, rsu_id, NOW_NS)
        payload, reason = verifier.verify(data, topic(rsu_id), NOW_NS)
        reasons.add(reason)
        if payload is not None:
            try:
                decode(payload, model)
                decoded += 1
            except CodecError:
                pass
    assert reasons <= EXPECTED[kind], reasons
    if kind == "signed_hostile":
        assert decoded < 40  # the hostile payloads are refused by the decoder, not the verifier
    elif kind in ("garbage_prefix", "truncated", "huge_fields"):
        assert "ok" not in reasons and len(reasons) >= 1
