"""V2V in the OBU pipeline (``obu_service.peers``): what a vehicle shares, how a peer's list is
screened, placed and fused (own slot bit), the peer clock exchange, and no echo."""

from collections import Counter

import numpy as np
import pytest

from v2i.core.frames import Pose2D, map_to_base_points
from v2i.core.objects import ObjectArray
from v2i.fusion.tracking import slot_source
from v2i.fusion.wire import states_from_objects
from obu_service.peers import MAX_PEERS, shared_list
from obu_service.pipeline import RSU_ID_BASE, ObuPipeline, ObuPipelineConfig
from obu_service.rsu_table import MAX_RSUS
from schemas.codec import decode, encode
from schemas.messages import SOURCE_RSU, SOURCE_VEHICLE, FusedObjectList

T0 = 1_767_225_600 * 10**9
MS = 1_000_000
POSE_A = Pose2D(0.0, 0.0, 0.0)  # A at the origin facing east
POSE_B = Pose2D(20.0, -10.0, np.pi / 2)  # B south-east of it, facing north


def dets(xy_base: np.ndarray) -> ObjectArray:
    """LiDAR detections (base_link) at ``xy_base`` (n, 2)."""
    n = len(xy_base)
    return ObjectArray(ids=np.arange(n), cls=np.ones(n, int), xy=np.asarray(xy_base, float), z=np.zeros(n),
                       lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=np.zeros(n), vxy=np.zeros((n, 2)),
                       cov_xy=np.tile(np.eye(2) * 0.2**2, (n, 1, 1)))


def pipeline(vid: str) -> ObuPipeline:
    p = ObuPipeline(ObuPipelineConfig(vehicle_id=vid, fusion="kf"))
    p.enable_v2v()
    return p


def sync(a: ObuPipeline, b: ObuPipeline, t_ns: int, offset_b_ns: int = 0, up_ms: float = 3.0,
         down_ms: float = 3.0) -> None:
    """One exchange a -> b -> a; b's clock reads offset_b_ns ahead of a's."""
    req = a.peers.make_time_request(t_ns)
    t2 = t_ns + round(up_ms * MS) + offset_b_ns
    reply = b.peers.answer(req, a.config.vehicle_id, t2, t2 + 50_000)
    a.peers.on_time_reply(reply, b.config.vehicle_id, t_ns + round((up_ms + down_ms) * MS) + 50_000)


def target_at(k: int) -> np.ndarray:
    return np.array([30.0 + 0.5 * k, 2.0])  # map, 5 m/s east


def run_pair(cycles: int = 25):
    """A sees the target, B does not; A's shared lists reach B 30 ms after A's publish.
    Returns (A's outputs, B's outputs, B's shared lists)."""
    a, b = pipeline("car-a"), pipeline("car-b")
    for k in range(6):  # clocks: a few exchanges each way, equal clocks
        t = T0 - 1_000 * MS + k * 100 * MS
        sync(a, b, t)
        sync(b, a, t)
    outs_a, outs_b, shared_b = [], [], []
    for k in range(cycles):
        t = T0 + k * 100 * MS
        a.on_pose(t, POSE_A)
        b.on_pose(t, POSE_B)
        a.on_detections(dets(map_to_base_points(target_at(k)[None], POSE_A)), t)
        out_a = a.fuse(t + 40 * MS)
        outs_a.append(out_a)
        b.peers.on_list(shared_list(out_a), "car-a", t + 70 * MS)
        b.on_detections(ObjectArray.empty(), t + 5 * MS)
        out_b = b.fuse(t + 80 * MS)
        outs_b.append(out_b)
        shared_b.append(shared_list(out_b))
        if shared_b[-1].objects:
            a.peers.on_list(shared_b[-1], "car-b", t + 95 * MS)
    return a, b, outs_a, outs_b, shared_b


def test_shared_list_keeps_only_own_perception():
    objs = dets(np.array([[5.0, 0.0], [10.0, 0.0], [15.0, 0.0]])).with_(
        sources=np.array([SOURCE_VEHICLE, SOURCE_RSU, SOURCE_VEHICLE | SOURCE_RSU]))
    out = FusedObjectList(vehicle_id="car-a", seq=1, cycle_time_ns=T0, publish_time_ns=T0 + 40 * MS,
                          objects=states_from_objects(objs, fused=True))
    assert [o.x for o in shared_list(out).objects] == [5.0, 15.0]


def test_shared_list_is_the_per_object_filter_of_the_output():
    """The columnar filter equals filtering the output's object models one by one and validating
    the list again (the wire bytes are the same), and a list of own objects only is passed through."""
    rng = np.random.default_rng(3)
    n = 40
    objs = dets(rng.uniform(-60.0, 60.0, (n, 2))).with_(
        vxy=rng.normal(0.0, 5.0, (n, 2)), yaw=rng.uniform(-np.pi, np.pi, n),
        sources=rng.choice([SOURCE_VEHICLE, SOURCE_RSU, SOURCE_VEHICLE | SOURCE_RSU], n))
    out = FusedObjectList(vehicle_id="car-a", seq=7, cycle_time_ns=T0, publish_time_ns=T0 + 40 * MS, ego_x=3.0,
                          ego_yaw=0.5, fusion="kf", mode="inter", objects=states_from_objects(objs, fused=True))
    fields = {name: getattr(out, name) for name in FusedObjectList.model_fields}
    reference = FusedObjectList.model_validate(
        {**fields, "objects": [o for o in out.objects if o.sources & SOURCE_VEHICLE]})
    shared = shared_list(out)
    assert 0 < len(shared.objects) < n
    assert encode(shared) == encode(reference)
    assert decode(encode(shared), FusedObjectList) == reference
    own_only = shared_list(shared)
    assert own_only is shared


def test_a_peer_list_gives_the_receiver_what_only_the_sender_sees():
    a, b, outs_a, outs_b, _ = run_pair()
    assert sum(len(o.objects) for o in outs_a[3:]) == len(outs_a) - 3  # A tracks its own detection
    seen = [k for k, o in enumerate(outs_b) if o.objects]
    assert seen and seen[0] <= 4
    for k in seen:
        obj = outs_b[k].objects[0]
        assert obj.sources == SOURCE_RSU  # a cooperative source, not B's own
        expected = map_to_base_points(target_at(k)[None], POSE_B)[0]
        assert np.hypot(obj.x - expected[0], obj.y - expected[1]) < 1.0, (k, obj.x, obj.y, expected)
    assert b.peers.table.get("car-a").index >= 16  # a peer slot after the RSU slots
    assert b.rejected == Counter()


def test_no_echo_a_vehicle_never_gets_its_own_objects_back():
    a, b, outs_a, outs_b, shared_b = run_pair()
    assert all(not s.objects for s in shared_b)  # B knows the target from A only: it shares nothing
    assert a.peers.table.get("car-b") is None or a.peers.table.get("car-b").accepted == 0
    assert all(o.sources == SOURCE_VEHICLE for out in outs_a for o in out.objects)
    # A's own list handed back to A is refused outright
    assert not a.peers.on_list(shared_list(outs_a[-1]), "car-a", T0 + 3_000 * MS)
    assert a.rejected["v2v_self"] == 1


def test_the_receiver_does_not_rely_on_the_sender_filtering():
    """A sender sharing its whole fused list (RSU-only objects included): those are dropped."""
    _, b, outs_a, _, _ = run_pair(8)
    objs = dets(np.array([[8.0, 0.0], [12.0, 1.0]])).with_(sources=np.array([SOURCE_RSU, SOURCE_VEHICLE]))
    fields = {name: getattr(outs_a[-1], name) for name in FusedObjectList.model_fields}
    bad = FusedObjectList.model_validate({**fields, "seq": 99, "objects": states_from_objects(objs, fused=True)})
    assert b.peers.on_list(bad, "car-a", outs_a[-1].publish_time_ns + 20 * MS)
    assert b.rejected["v2v_not_own_perception"] == 1
    state = b.peers.table.get("car-a")
    frame = state.frames[-1].objects
    assert len(frame) == 1 and frame.sources[0] == slot_source(state.index)
    assert frame.ids[0] // RSU_ID_BASE == state.index + 1


@pytest.mark.parametrize("change, reason", [
    ({"vehicle_id": "car-c"}, "v2v_key_mismatch"),
    ({"frame_id": "map"}, "v2v_bad_frame"),
    ({"publish_time_ns": T0 - 1}, "v2v_bad_header"),
])
def test_bad_peer_lists_are_refused_and_counted(change, reason):
    p = pipeline("car-b")
    msg = FusedObjectList(vehicle_id="car-a", seq=1, cycle_time_ns=T0, publish_time_ns=T0 + 40 * MS)
    fields = {name: getattr(msg, name) for name in FusedObjectList.model_fields}
    assert not p.peers.on_list(FusedObjectList.model_construct(**{**fields, **change}), "car-a", T0 + 60 * MS)
    assert p.rejected[reason] == 1


def test_a_duplicate_and_too_many_peers_are_refused():
    p = ObuPipeline(ObuPipelineConfig(vehicle_id="me"))
    p.enable_v2v(max_peers=2)
    for i in range(3):
        msg = FusedObjectList(vehicle_id=f"p{i}", seq=1, cycle_time_ns=T0, publish_time_ns=T0 + 40 * MS)
        p.peers.on_list(msg, f"p{i}", T0 + 60 * MS)
    assert p.peers.on_list(msg.model_copy(update={"vehicle_id": "p1"}), "p1", T0 + 61 * MS) is False
    assert len(p.peers.table) == 2  # p2 took the slot of a peer that was not established
    assert p.rejected["v2v_duplicate"] == 1


def test_peer_slots_must_fit_in_the_source_bits():
    p = ObuPipeline(ObuPipelineConfig(known_rsus={f"r{i}": (0.0, 0.0) for i in range(40)}, max_unknown_rsus=16))
    p.enable_v2v(max_peers=MAX_RSUS - 56)
    with pytest.raises(ValueError, match="exceed the 62"):
        p.enable_v2v(max_peers=MAX_RSUS - 55)
    assert MAX_PEERS >= 1


def test_peer_clock_offset_is_learned_from_time_exchanges():
    """B's clock is 37.5 ms ahead; symmetric 3 ms delays: estimate within its bound, close to the truth."""
    a, b = pipeline("car-a"), pipeline("car-b")
    for k in range(8):
        sync(a, b, T0 + k * 100 * MS, offset_b_ns=37_500_000, up_ms=3.0, down_ms=3.0 + 0.2 * (k % 3))
    a.peers.frames(T0 + 2_000 * MS)  # the held replies ripen
    est = a.peers.clock_offset("car-b", T0 + 2_000 * MS)
    assert est is not None and abs(est.offset_ns - 37_500_000) <= max(est.uncertainty_ns, 1) + 1_000
    assert est.uncertainty_ns <= 3.5 * MS  # half the round trip: the asymmetry is not observable
    summary = a.peers.summary(T0 + 2_000 * MS)["car-b"]
    assert summary["sync_samples"] >= 4 and abs(summary["clock_offset_ms"] - 37.5) < 0.2
    # a reply whose body names another vehicle than its key is refused
    req = a.peers.make_time_request(T0 + 3_000 * MS)
    a.peers.on_time_reply(b.peers.answer(req, "car-a", T0 + 3_001 * MS, T0 + 3_001 * MS), "car-c", T0 + 3_002 * MS)
    assert a.rejected["v2v_time_reply_key_mismatch"] == 1
    assert b.peers.answer(req, "car-x", T0, T0) is None and b.rejected["v2v_time_request_key_mismatch"] == 1


def test_the_node_shell_counts_what_it_cannot_read():
    from obu_service.v2v_shell import V2vShell
    from v2i.runtime.intake import Item
    from v2i.sim.clock import SimClock

    p = ObuPipeline(ObuPipelineConfig(vehicle_id="ego"))
    shell = V2vShell("ego", p.enable_v2v(), SimClock(T0), 1 << 18)
    shell.handle(Item("v2v_objects", "v2x/v2v/a.b/objects", b"\x00", T0))  # Zenoh allows ids we do not
    shell.handle(Item("v2v_objects", "v2x/v2v/car-a/objects", b"\x00", T0))
    shell.handle(Item("v2v_reply", "v2x/v2v/ego/time_reply/ego", b"\x00", T0))
    assert p.rejected == Counter({"v2v_bad_sender_key": 1, "v2v_malformed": 2})


def test_hostile_v2v_messages_never_raise_past_the_codec():
    """Every hostile kind around every V2V message: decoded ones go through the intake without raising."""
    from v2i.adversary.fuzz_v2v import V2V_TYPES, V2vHostile
    from v2i.adversary.hostile import KINDS
    from schemas.codec import CodecError, decode
    from schemas.messages import TimeReply, TimeRequest

    a = pipeline("ego")
    a.on_pose(T0, POSE_A)
    hostile = V2vHostile(np.random.default_rng(2), "x0", "x0")
    models = {"fused_object_list": FusedObjectList, "time_request": TimeRequest, "time_reply": TimeReply}
    decoded = Counter()
    for kind in KINDS:
        for typ in V2V_TYPES:
            for _ in range(5):
                try:
                    msg = decode(hostile.make(kind, typ, T0), models[typ], 1 << 18)
                except CodecError:
                    continue
                decoded[typ] += 1
                if typ == "fused_object_list":
                    a.peers.on_list(msg, "x0", T0)
                elif typ == "time_request":
                    a.peers.answer(msg, "x0", T0, T0)
                else:
                    a.peers.on_time_reply(msg, "x0", T0)
    assert min(decoded.values()) > 0
    a.on_detections(ObjectArray.empty(), T0)
    out = a.fuse(T0 + 10 * MS)  # fusing whatever was admitted does not raise either
    assert out.vehicle_id == "ego"


def test_peer_lists_keep_no_link_statistics():
    """A peer's lists are fused inter-frame only and nothing reads a peer's link statistics: none are
    kept, of an accepted list or a stale one (refused and counted as before)."""
    a, b, outs_a, _, _ = run_pair()
    state = b.peers.table.get("car-a")
    assert state.accepted > 0 and state.monitor.summary()["messages"] == 0
    old = shared_list(outs_a[0]).model_copy(update={"seq": 999})  # unseen, captured at T0
    assert not b.peers.on_list(old, "car-a", T0 + 5_000 * MS)
    assert b.rejected["v2v_stale"] == 1 and state.monitor.summary()["messages"] == 0
