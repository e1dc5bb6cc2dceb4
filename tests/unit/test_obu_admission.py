"""Hostile or broken RSU input against the OBU pipeline: admitted input never crashes fusion,
refused input is counted by reason, and a flood of names never locks a real RSU out."""

import numpy as np
import pytest

from v2i.core.frames import Pose2D
from v2i.core.objects import ObjectArray
from v2i.fusion.wire import fit_to_wire, states_from_objects
from schemas.wire_view import pack_view, unpack_view
from obu_service.pipeline import ObuPipeline, ObuPipelineConfig
from obu_service.rsu_table import RsuTable
from v2i.clock.time_requests import TimeRequests
from rsu_service.pipeline import answer_time_request
from schemas.codec import SchemaVersionError, decode, encode
from schemas.messages import (MAX_OBJECTS, SCHEMA_VERSION, FusedObjectList, ObjectList, ObjectListHeader,
                              PredictedPath, PredictionList, TimeReply)

T0 = 1_767_225_600 * 10**9
THETA = 350_000_000  # rsu clock - obu clock
MS = 1_000_000
RSU_XY = (0.0, -20.0)


def objs(xy) -> ObjectArray:
    xy = np.atleast_2d(np.asarray(xy, float))
    n = len(xy)
    return ObjectArray(ids=np.arange(1, n + 1), cls=np.ones(n, int), xy=xy, z=np.full(n, 0.75),
                       lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=np.zeros(n), vxy=np.zeros((n, 2)))


def pipeline(**cfg) -> ObuPipeline:
    """Synced with rsu1 (known, at RSU_XY) at T0; the ego at the origin facing east."""
    config = {"fusion": "iou-merge", "known_rsus": {"rsu1": RSU_XY}, **cfg}
    p = ObuPipeline(ObuPipelineConfig(**config))
    sync(p, "rsu1", T0)
    p.on_pose(T0, Pose2D(0.0, 0.0, 0.0))
    return p


def sync(p: ObuPipeline, rsu_id: str, t_ns: int) -> None:
    """One exchange at t_ns; the pipeline holds the reply 150 ms before its clock filter sees it."""
    req = p.make_time_request(t_ns)
    p.on_time_reply(answer_time_request(req, rsu_id, t_ns + 5 * MS + THETA, t_ns + 5 * MS + THETA), t_ns + 10 * MS)


def header(capture_obu_ns: int, seq: int = 0, rsu_id: str = "rsu1", **fields) -> ObjectListHeader:
    return ObjectListHeader(rsu_id=rsu_id, seq=seq, capture_time_ns=capture_obu_ns + THETA,
                            publish_time_ns=capture_obu_ns + THETA + 50 * MS, **fields)


def rsu_list(capture_obu_ns: int, xy, seq: int = 0, rsu_id: str = "rsu1", **fields) -> ObjectList:
    return ObjectList(header=header(capture_obu_ns, seq, rsu_id, **fields), objects=states_from_objects(objs(xy)))


def cycle(p: ObuPipeline, t_ns: int, own_xy=((10.0, 0.0),)) -> FusedObjectList:
    p.on_pose(t_ns, Pose2D(0.0, 0.0, 0.0))
    p.on_detections(objs(own_xy), t_ns)
    out = p.fuse(t_ns + 60 * MS)
    assert decode(encode(out), FusedObjectList) == out  # whatever is published encodes
    return out


# --- item 2: admitted input never crashes fusion ---------------------------------------------------

@pytest.mark.parametrize("fusion", ["iou-merge", "kf", "nms", "tclf", "rsu-only"])
def test_an_object_a_million_metres_away_is_dropped_not_fatal(fusion):
    p = pipeline(fusion=fusion)
    t = T0 + 1_000 * MS
    p.on_rsu_message(rsu_list(t - 150 * MS, [[-1e6, 0.0], [5.0, -20.0]]), t - 20 * MS)
    out = cycle(p, t)
    assert p.rejected["object_outside_site"] == 1
    assert any(o.y == pytest.approx(-20.0, abs=1.0) for o in out.objects)  # the real one is fused


def test_unknown_rsu_objects_are_bounded_around_the_ego_and_output_is_total():
    """No position known for the RSU: the site radius is taken around the ego; and even an
    object the site check could not see (no pose yet) cannot break the output."""
    p = ObuPipeline(ObuPipelineConfig(fusion="rsu-only"))  # no known RSUs, no pose yet
    sync(p, "stranger", T0)
    t = T0 + 1_000 * MS
    p.on_rsu_message(rsu_list(t - 150 * MS, [[-1e6, 0.0], [1e6, 1e6]], rsu_id="stranger"), t - 20 * MS)
    p.on_pose(t, Pose2D(5e5, 0.0, np.pi))  # base_link x of the objects: up to 1.5e6 m
    p.on_detections(objs([[10.0, 0.0]]), t)
    out = p.fuse(t + 60 * MS)
    assert decode(encode(out), FusedObjectList) == out
    assert p.output_dropped["out_of_range"] >= 1


def test_more_objects_than_the_output_holds_are_truncated_nearest_first():
    p = pipeline(fusion="iou-merge", max_objects_per_list=1024, site_radius_m=1e5)
    t = T0 + 1_000 * MS
    far = np.column_stack([np.arange(1024) * 10.0 + 30.0, np.full(1024, -60.0)])  # (1024, 2)
    p.on_rsu_message(rsu_list(t - 150 * MS, far), t - 20 * MS)
    out = cycle(p, t, own_xy=[[10.0 + 6.0 * k, 30.0] for k in range(50)])
    assert len(out.objects) == MAX_OBJECTS
    assert p.output_dropped["truncated"] == 1024 + 50 - MAX_OBJECTS
    assert max(np.hypot(o.x, o.y) for o in out.objects) < 10.0 * 1024  # the farthest went


def test_fit_to_wire_clips_drops_and_never_raises():
    o = objs([[0.0, 0.0], [2e6, 0.0], [np.nan, 1.0], [3.0, 3.0]])
    o = o.with_(vxy=np.array([[300.0, -300.0], [0, 0], [0, 0], [1.0, 1.0]]), yaw=np.array([50.0, 0, 0, 0]),
                lwh=np.array([[200.0, 1, 1], [1, 1, 1], [1, 1, 1], [1, 1, 1]]), ids=np.array([-1, 2, 3, 2**33]))
    fitted, counts = fit_to_wire(o)
    assert counts == {"not_finite": 1, "out_of_range": 1, "clipped": 2}
    states = states_from_objects(fitted, fused=True)
    assert [s.vx for s in states] == [200.0, 1.0] and states[0].length == 100.0
    assert states[0].id == 2**32 - 1 and states[1].id == 0


# --- item 8: freshness, duplicates, versions ----------------------------------------------------------

def test_future_stamped_and_over_predicted_lists_are_refused():
    p = pipeline()
    t = T0 + 1_000 * MS
    p.on_rsu_message(rsu_list(t + 900 * MS, [[5.0, -20.0]]), t)  # stamped 0.9 s after it arrived
    p.on_rsu_message(rsu_list(t - 100 * MS, [[5.0, -20.0]], seq=1, prediction_ns=10_000 * MS), t)
    assert p.rejected["future_timestamp"] == 1 and p.rejected["prediction_too_long"] == 1
    assert cycle(p, t + 10 * MS).mode == "vehicle-only"


def test_future_stamped_paths_cannot_drive_the_obu_into_planning():
    p = pipeline()
    t = T0 + 1_000 * MS
    paths = PredictionList(header=header(t + 900 * MS), objects=states_from_objects(objs([[5.0, -20.0]])),
                           paths=(PredictedPath(id=1, x=[5.0] * 50, y=[-20.0] * 50, yaw=[0.0] * 50),))
    p.on_predictions(paths, t)
    assert p.rejected["future_timestamp"] == 1
    assert cycle(p, t + 10 * MS).mode == "vehicle-only"


def test_replays_are_duplicates_or_stale_and_a_restarted_rsu_is_accepted():
    p = pipeline()
    t = T0 + 1_000 * MS
    genuine = rsu_list(t - 150 * MS, [[5.0, -20.0]], seq=7)
    p.on_rsu_message(genuine, t - 30 * MS)
    p.on_rsu_message(genuine, t)  # replayed at once
    p.on_rsu_message(genuine, t + 5_000 * MS)  # replayed 5 s later
    p.on_rsu_message(rsu_list(t - 150 * MS, [[5.0, -20.0]], seq=8), t + 5_000 * MS)  # unseen, 5 s old
    assert p.rejected["duplicate"] == 2 and p.rejected["stale"] == 1
    assert p._rsus.get("rsu1").monitor.summary()["messages"] == 2  # the stale list still told its delay
    restarted = rsu_list(t + 5_000 * MS - 150 * MS, [[5.0, -20.0]], seq=0)  # seq starts again
    p.on_rsu_message(restarted, t + 5_000 * MS - 20 * MS)
    assert p.rejected["duplicate"] == 2 and cycle(p, t + 5_000 * MS).mode in ("intra", "inter")


def test_a_header_of_another_schema_version_is_refused_as_such():
    msg = rsu_list(T0, [[1.0, 2.0]])
    view = unpack_view(encode(msg))
    view["d"]["header"]["schema_version"] = SCHEMA_VERSION + 1
    wire = pack_view(view)
    with pytest.raises(SchemaVersionError, match=f"schema version {SCHEMA_VERSION + 1}"):
        decode(wire, ObjectList)


def test_lists_with_too_many_objects_are_refused_before_decoding():
    p = pipeline(max_objects_per_list=4)
    assert p.admit_list(header(T0 + 500 * MS), 5, T0 + 600 * MS) is None
    assert p.admit_list(header(T0 + 500 * MS), 4, T0 + 600 * MS) is not None
    assert p.rejected == {"too_many_objects": 1}


# --- item 4: the RSU table -----------------------------------------------------------------------------

def test_a_flood_of_fake_ids_never_locks_out_a_registered_rsu():
    p = ObuPipeline(ObuPipelineConfig(fusion="iou-merge", known_rsus={"rsu1": RSU_XY}, max_unknown_rsus=8))
    t = T0 + 1_000 * MS
    for k in range(64):
        p.on_rsu_message(rsu_list(t - 150 * MS, [[5.0, -20.0]], rsu_id=f"fake{k}"), t)
    assert p.rejected["too_many_rsus"] == 0  # non-established strangers take each other's slots
    sync(p, "rsu1", t)
    p.on_rsu_message(rsu_list(t + 100 * MS, [[5.0, -20.0]]), t + 200 * MS)
    assert {s.rsu_id for s in p.metrics(t).rsus} >= {"rsu1"} and len(p.metrics(t).rsus) == 9
    assert cycle(p, t + 210 * MS).mode in ("intra", "inter")


def test_unknown_rsus_expire_and_established_ones_keep_their_slot():
    table = RsuTable({"rsu1": RSU_XY}, max_unknown=2, expiry_ns=10_000 * MS)
    a = table.admit("a", T0)
    table.admit("b", T0)
    a.accepted = 1
    a.sync.add(_sample(T0))  # a is established: synced, data accepted
    assert table.admit("c", T0 + 1 * MS).rsu_id == "c"  # evicts b, the stranger
    assert table.get("b") is None and table.get("a") is a
    c = table.get("c")
    c.accepted = 1
    c.sync.add(_sample(T0))
    assert table.admit("d", T0 + 2 * MS) == "too_many_rsus"  # both unknown slots established
    assert table.admit("rsu1", T0 + 3 * MS).known  # known ids are always admitted
    assert sorted(table.expire(T0 + 10_002 * MS)) == ["a", "c"]  # rsu1 heard at T0 + 3 ms stays
    assert table.admit("d", T0 + 10_002 * MS).index == 0  # freed indices are reused
    assert RsuTable(accept_unknown=False).admit("x", T0) == "unknown_rsu"


def _sample(t_ns):
    from v2i.clock.clock_sync import SyncSample

    return SyncSample(t_ns, t_ns + 5 * MS, t_ns + 5 * MS, t_ns + 10 * MS)


def test_too_many_rsu_slots_is_a_config_error():
    with pytest.raises(ValueError, match="RSU slots"):
        ObuPipelineConfig(known_rsus={f"r{k}": (0.0, 0.0) for k in range(60)}, max_unknown_rsus=8)


# --- time replies ------------------------------------------------------------------------------------------

def test_each_rsu_answers_a_request_once_and_late_replies_still_match():
    requests = TimeRequests("ego", hold_ns=150 * MS)
    req = requests.make(T0)
    for k in range(1, 300):  # 30 s of requests at 10 Hz
        requests.make(T0 + k * 100 * MS)
    reply = answer_time_request(req, "rsu1", T0 + 5 * MS, T0 + 6 * MS)
    late_ns = T0 + 30_000 * MS
    assert requests.match(reply, late_ns) is None  # 30 s late, still matched
    assert requests.ripe(late_ns + 149 * MS) == []  # held
    [(rsu_id, sample)] = requests.ripe(late_ns + 150 * MS)
    assert rsu_id == "rsu1" and (sample.t1_ns, sample.t2_ns, sample.t4_ns) == (T0, T0 + 5 * MS, late_ns)
    assert requests.match(reply, late_ns + 200 * MS) == "time_reply_duplicate"
    other = answer_time_request(req, "rsu2", T0 + 5 * MS, T0 + 6 * MS)
    assert requests.match(other, late_ns) is None  # another RSU may answer the same request
    stray = TimeReply(rsu_id="rsu1", seq=10_000, t1_ns=T0, t2_ns=T0, t3_ns=T0)
    assert requests.match(stray, T0) == "time_reply_unmatched" and len(requests) == 300
    assert len(TimeRequests("ego", capacity=8).make(T0).model_dump()) and len(TimeRequests("ego")) == 0


@pytest.mark.parametrize("forged_first", [True, False])
def test_a_forged_reply_and_the_genuine_one_void_each_other(forged_first):
    """Whichever comes first, two different replies from one RSU id to one request are both
    dropped; only a reply nobody contradicted within the hold reaches the clock filter."""
    requests = TimeRequests("ego", hold_ns=150 * MS)
    req = requests.make(T0)
    genuine = answer_time_request(req, "rsu1", T0 + 5 * MS + THETA, T0 + 6 * MS + THETA)
    forged = genuine.model_copy(update={"t2_ns": genuine.t2_ns - 245 * MS, "t3_ns": genuine.t3_ns - 245 * MS})
    first, second = (forged, genuine) if forged_first else (genuine, forged)
    assert requests.match(first, T0 + 2 * MS) is None
    assert requests.match(second, T0 + 40 * MS) == "time_reply_conflict"
    assert requests.ripe(T0 + 1_000 * MS) == []
    clean = requests.make(T0 + 100 * MS)
    requests.match(answer_time_request(clean, "rsu1", T0 + 105 * MS, T0 + 106 * MS), T0 + 110 * MS)
    assert [s.t1_ns for _, s in requests.ripe(T0 + 1_000 * MS)] == [T0 + 100 * MS]


def test_pipeline_counts_conflicts_and_keeps_its_clock():
    p = pipeline()
    t = T0 + 1_000 * MS
    req = p.make_time_request(t)
    genuine = answer_time_request(req, "rsu1", t + 5 * MS + THETA, t + 5 * MS + THETA)
    p.on_time_reply(genuine.model_copy(update={"t2_ns": genuine.t2_ns + 245 * MS, "t3_ns": genuine.t3_ns + 245 * MS}),
                    t + 2 * MS)
    p.on_time_reply(genuine, t + 10 * MS)
    p.on_detections(objs([[10.0, 0.0]]), t + 500 * MS)
    assert p.rejected["time_reply_conflict"] == 1
    assert abs(p.clock_offset("rsu1", t).offset_ns - THETA) < 1 * MS


# --- item 10: the intra slot does not depend on the sign of a sub-ms clock error ----------------------

@pytest.mark.parametrize("error_us", [-400, -50, 0, 50, 400])
def test_a_capture_at_the_cycle_instant_is_its_slot_whatever_the_clock_error(error_us):
    """RSU (5 Hz) and LiDAR (10 Hz) capture in phase; the OBU's idea of the RSU clock is off by
    error_us. The frame captured at the cycle's instant is the slot's, for either sign."""
    p = pipeline(fusion_mode="intra")
    t, e = T0 + 1_000 * MS, error_us * 1_000
    for k, capture in enumerate((t - 400 * MS, t - 200 * MS)):
        p.on_rsu_message(rsu_list(capture + e, [[5.0, -20.0]], seq=k), capture + 150 * MS)
    p.on_pose(t, Pose2D(0.0, 0.0, 0.0))
    p.on_detections(objs([[10.0, 0.0]]), t)
    assert p._cycle.intra_slots == {"rsu1": t + e}  # waits for the frame captured at its own instant
    assert not p.ready(t + 60 * MS)
    p.on_rsu_message(rsu_list(t + e, [[5.0, -20.0]], seq=2), t + 70 * MS)
    assert p.ready(t + 70 * MS) and p.fuse(t + 70 * MS).mode == "intra"


def test_paths_are_bounded_in_points_and_kept_only_once_the_clock_is_known():
    p = pipeline(max_path_points=100)
    t = T0 + 1_000 * MS
    h = header(t - 100 * MS)
    assert p.admit_paths(h, 4, 101, t) is None and p.admit_paths(h, 4, 100, t) is not None
    unsynced = ObuPipeline(ObuPipelineConfig(fusion="iou-merge"))
    paths = PredictionList(header=h, objects=states_from_objects(objs([[5.0, -20.0]])),
                           paths=(PredictedPath(id=1, x=[5.0] * 50, y=[-20.0] * 50, yaw=[0.0] * 50),))
    unsynced.on_predictions(paths, t)
    assert p.rejected == {"too_many_path_points": 1} and unsynced.rejected == {"paths_before_clock_sync": 1}


def test_the_rsu_detection_of_the_ego_itself_is_dropped_and_counted():
    """An RSU sees the vehicles it serves: the object on the ego's own footprint (at the list's
    capture time) is the ego, never an obstacle; one just beyond the footprint + margin stays."""
    p = pipeline(ego_size_m=(4.0, 2.0), self_margin_m=1.0)
    t = T0 + 400 * MS
    p.on_pose(t - 100 * MS, Pose2D(10.0, 0.0, np.pi / 2))  # the ego at capture time: at (10, 0) facing north
    p.on_pose(t, Pose2D(10.0, 5.0, np.pi / 2))  # and 5 m farther on when the list arrives
    p.on_rsu_message(rsu_list(t - 100 * MS, [(10.5, 2.5), (13.2, 0.0), (10.0, 5.0)]), t)
    assert p.rejected["ego_self_detection"] == 1
    # (10.5, 2.5): 2.5 m ahead, 0.5 m right: inside 3 x 2 m half extents -> itself;
    # (13.2, 0) is 3.2 m to its right (beyond 2 m) and (10, 5) 5 m ahead (beyond 3 m) -> kept
    out = cycle(p, t + 50 * MS, own_xy=((60.0, 60.0),))
    assert len(out.objects) == 3  # its own far object and the two RSU objects that are not itself


def test_time_queries_start_early_enough_to_sync_before_the_run():
    """Queries begin a second before the run (the first reply is held 150 ms before the clock
    filter sees it), never in the past, and stop at the run's end."""
    from v2i.clock.time_requests import sync_times_ns

    start = T0 + 20_000 * MS
    early = sync_times_ns(T0, start, 2.0, 10.0)
    assert early[0] == start - 1_000 * MS and early[-1] < start + 2_000 * MS
    assert np.all(np.diff(early) == 100 * MS) and len(early) == 30
    late = sync_times_ns(start - 300 * MS, start, 2.0, 10.0)
    assert late[0] == start - 300 * MS
    assert sync_times_ns(T0, start, 2.0, 0.5)[0] == start - 4_000 * MS  # at least two periods


def test_on_site_keeps_the_points_within_the_radius_by_np_hypot():
    """on_site keeps exactly the rows with np.hypot(p - c) <= radius (on random sites, points on the circle and
    an ulp or two either side, signed zeros, NaN and inf), counts the others, and returns the very list when
    it keeps every row."""
    from collections import Counter

    from obu_service.admission import Admission, Limits

    rng = np.random.default_rng(23)
    whole = 0
    for trial in range(4000):
        centre = rng.uniform(-3000.0, 3000.0, 2) if trial % 5 else np.array([0.0, -0.0])
        radius = float(rng.choice([2000.0, 150.0, rng.uniform(1.0, 500.0)]))
        n = int(rng.integers(1, 25))
        xy = centre + rng.uniform(-1.0, 1.0, (n, 2)) * radius * rng.choice([0.5, 0.7071])
        if trial % 2:  # points on the circle, nudged by a few ulps
            angle = rng.uniform(-np.pi, np.pi, 3)
            ring = centre + radius * np.column_stack([np.cos(angle), np.sin(angle)])
            for _ in range(int(rng.integers(0, 3))):
                ring = np.nextafter(ring, rng.choice([-np.inf, np.inf], ring.shape))
            xy = np.concatenate([xy, ring])
        if trial % 97 == 5:
            xy[0] = [np.nan, 0.0] if trial % 2 else [np.inf, 1.0]
        if trial % 10 == 3:
            xy[-1] = [-0.0, 0.0]
        within = np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1]) <= radius
        whole += within.all()
        rejected = Counter()
        admission = Admission(Limits(256, 8192, 0, 0, 0, 0, radius), RsuTable({"r": tuple(centre)}), rejected)
        state = admission._rsus.admit("r", 0)
        points = objs(xy)
        kept = admission.on_site(state, points, None)
        assert np.array_equal(kept.xy, xy[within], equal_nan=True) and rejected["object_outside_site"] == (~within).sum()
        assert (kept is points) == within.all()
    assert 1000 < whole < 4000  # both cases, many times
