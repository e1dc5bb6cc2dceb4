"""The fuzz command's hostile inputs: every kind is refused by the codec with a CodecError
or decodes to a valid message (whose handling the pipelines must survive), never anything else."""

import numpy as np
import pytest

from v2i.adversary.hostile import KINDS, TARGET_TYPES, HostileInputs
from schemas import messages as m
from schemas.codec import CodecError, decode

T0 = 1_767_225_600 * 10**9
MODELS = {"object_list": m.ObjectList, "prediction_list": m.PredictionList, "time_request": m.TimeRequest,
          "time_reply": m.TimeReply, "ego_pose": m.EgoPose, "link_control": m.LinkControl}


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_every_hostile_kind_is_a_codec_error_or_a_valid_message(kind):
    hostile = HostileInputs(np.random.default_rng(7))
    outcomes = set()
    for typ in TARGET_TYPES:
        for _ in range(12):
            payload = hostile.make(kind, typ, T0)
            assert isinstance(payload, bytes)
            try:
                outcomes.add(type(decode(payload, MODELS[typ])).__name__)
            except CodecError as exc:
                outcomes.add(exc.reason)
    if kind in ("random_bytes", "truncated", "wrong_shapes", "non_finite", "header_version", "unknown_keys"):
        assert outcomes <= {"malformed", "invalid", "version", "wrong_type", "too_large"}, outcomes


def test_valid_messages_are_valid_and_extreme_ones_stay_within_the_wire():
    hostile = HostileInputs(np.random.default_rng(1))
    for typ, model in MODELS.items():
        decode(hostile.valid(typ, T0), model)
    extreme = decode(hostile.extreme_values("object_list", T0), m.ObjectList)
    assert max(abs(o.x) for o in extreme.objects) > 1e5 and {abs(o.vx) for o in extreme.objects} == {200.0}


def test_the_fuzzers_valid_cpm_lands_in_the_targets_map():
    """A 'valid' hostile CPM is placed at the target's site origin: its objects decode where they were put
    (within +-80 m of the origin), not near 0 N 0 E (~930 km away from a site at 49 N 8.4 E)."""
    import time

    from schemas import cpm
    from v2i.adversary.fuzz_standard import StandardHostile

    origin = (49.0, 8.4)
    payload = StandardHostile(np.random.default_rng(3), origin=origin).valid("cpm", time.time_ns())
    _, cols = cpm.decode(payload, "x1", origin=origin)
    assert len(cols["x"]) == 8 and np.all(np.abs(cols["x"]) <= 80.01) and np.all(np.abs(cols["y"]) <= 80.01)
