"""The image-level OBU (``ImageFusionNode``, ``v2i obu --fusion roif``) verifies and unwraps signed
RSU time replies and feature frames as the object-level node does (``inbound_security``). The
node's loop step ``_handle_input`` is driven directly: no Zenoh, times are arguments."""

from __future__ import annotations

import time

import numpy as np
import pytest

from v2i.fusion.roif_features import ViewFeatures
from obu_service.config import ObuConfig
from obu_service.image_fusion_node import ImageFusionNode
from schemas import keys
from schemas.codec import encode
from schemas.image_messages import RsuImageFeatures
from v2i.runtime.intake import Item
from schemas.messages import TimeReply
from v2i.security.envelope import Signer
from v2i.security.pki import load_signer
from v2i.security.site import write_site
from v2i.services import obu_node

SCENARIO, RSU_ID = "roif-intersection", "rsu-roif"
THETA_NS = 25_000_000  # rsu - obu
PERIOD_NS = 100_000_000


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    directory = tmp_path_factory.mktemp("pki")
    write_site(directory, time.time_ns(), [RSU_ID], ["ego"])
    return directory, Signer(load_signer(directory, RSU_ID)), Signer(load_signer(directory, "ego"))


def _node(pki_dir=None) -> ImageFusionNode:
    return obu_node(ObuConfig(scenario=SCENARIO, fusion="roif", roif_threads=1,
                              pki_dir=None if pki_dir is None else str(pki_dir)))


def _exchange(node: ImageFusionNode, t1_ns: int, sign=None) -> Item:
    """A time reply to a fresh request of ``node`` at OBU time t1 (1 ms each way), signed by ``sign``."""
    request = node.pipeline.make_time_request(t1_ns)
    t_rsu_ns = t1_ns + 1_000_000 + THETA_NS
    reply = encode(TimeReply(rsu_id=RSU_ID, seq=request.seq, t1_ns=t1_ns, t2_ns=t_rsu_ns, t3_ns=t_rsu_ns))
    key = keys.rsu_time(RSU_ID)
    return Item("time", key, reply if sign is None else sign.sign(reply, t_rsu_ns, key), t1_ns + 2_000_000)


def _features(t_rsu_ns: int, seq: int, sign: Signer | None, generation_ns: int | None = None) -> Item:
    empty = ViewFeatures.of(np.zeros((0, 4)), [], [], np.zeros((0, 2)), np.zeros((0, 32)), (640, 480))
    data = encode(RsuImageFeatures.from_view(RSU_ID, seq, t_rsu_ns, empty))
    key = keys.rsu_image_features(RSU_ID)
    if sign is not None:
        data = sign.sign(data, t_rsu_ns if generation_ns is None else generation_ns, key)
    return Item("features", key, data, t_rsu_ns - THETA_NS + 30_000_000)


def _synced(node: ImageFusionNode, signer: Signer | None, t0_ns: int, n: int = 20) -> int:
    """``n`` exchanges 100 ms apart; returns the OBU time after them."""
    for i in range(n):
        node._handle_input(_exchange(node, t0_ns + i * PERIOD_NS, signer))
    return t0_ns + n * PERIOD_NS


def test_strict_roif_node_unwraps_signed_time_replies_and_features(site):
    directory, rsu, _ = site
    node = _node(directory)
    t_ns = _synced(node, rsu, time.time_ns())
    estimate = node.pipeline.clock_offset(RSU_ID, t_ns)
    assert estimate is not None and abs(estimate.offset_ns - THETA_NS) < 100_000
    assert node._handle_input(_features(t_ns + THETA_NS, 1, rsu)) is None
    assert node.pipeline.accepted == 1
    assert not [r for r in node.pipeline.rejected if r.startswith("security")], node.pipeline.rejected


def test_strict_roif_node_drops_unsigned_forged_wrong_role_and_stale(site):
    directory, rsu, vehicle = site
    node = _node(directory)
    t0_ns = time.time_ns()
    _synced(node, None, t0_ns, n=5)  # unsigned replies: dropped before they reach the clock
    assert node.pipeline.clock_offset(RSU_ID, t0_ns) is None
    assert node.pipeline.rejected["security_unsigned"] == 5
    forged = _exchange(node, t0_ns + 6 * PERIOD_NS, rsu)
    forged = Item(forged.kind, forged.source, forged.payload[:-1] + bytes([forged.payload[-1] ^ 1]), forged.receive_ns)
    node._handle_input(forged)
    assert node.pipeline.rejected["security_bad_signature"] == 1
    t_ns = _synced(node, rsu, t0_ns + 10 * PERIOD_NS)
    node._handle_input(_features(t_ns + THETA_NS, 1, vehicle))  # a vehicle's certificate: RSU messages are RSUs' only
    node._handle_input(_features(t_ns + THETA_NS, 2, None))
    node._handle_input(_features(t_ns + THETA_NS, 3, rsu, generation_ns=t_ns + THETA_NS - 3_000_000_000))  # > 2 s old
    rejected = node.pipeline.rejected
    assert (rejected["security_wrong_role"], rejected["security_unsigned"], rejected["security_stale"]) == (1, 6, 1)
    assert node.pipeline.accepted == 0


def test_roif_node_without_a_pki_takes_envelopes_unchecked(site):
    _, rsu, _ = site
    node = _node()
    t_ns = _synced(node, rsu, time.time_ns())  # signed replies unwrapped under "off"
    assert node.pipeline.clock_offset(RSU_ID, t_ns) is not None
    node._handle_input(_features(t_ns + THETA_NS, 1, None))
    assert node.pipeline.accepted == 1 and not any(r.startswith("security") for r in node.pipeline.rejected)


def test_a_feature_frame_handled_after_newer_time_replies_is_not_stale(site):
    """The loop may take an item well after its receipt (it renders its own camera meanwhile) and
    serves sources in turn: a frame received fresh, handled after 3 s of newer replies from the
    same RSU certificate, is one stream behind another, not a replay nor stale."""
    directory, rsu, _ = site
    node = _node(directory)
    t0_ns = time.time_ns()
    t_ns = _synced(node, rsu, t0_ns, n=31)  # replies generated up to t0 + 3 s (RSU clock)
    frame = _features(t0_ns + 200_000_000 + THETA_NS, 1, rsu)  # generated at t0 + 0.2 s, received 30 ms later
    assert frame.receive_ns < t_ns - 2_000_000_000
    node._handle_input(frame)
    assert node.pipeline.accepted == 1, node.pipeline.rejected
