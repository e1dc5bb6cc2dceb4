import numpy as np
import pytest

from v2i.core.frames import Pose2D
from v2i.core.objects import ObjectArray
from v2i.fusion.wire import states_from_objects
from obu_service.pipeline import ObuPipeline, ObuPipelineConfig
from rsu_service.pipeline import answer_time_request
from schemas.messages import SOURCE_RSU, SOURCE_VEHICLE, ObjectList, ObjectListHeader, PredictedPath, PredictionList

T0 = 1_767_225_600 * 10**9
THETA = 350_000_000  # rsu clock - obu clock
MS = 1_000_000


def objs(xy, vxy=None, ids=None):
    xy = np.atleast_2d(np.asarray(xy, float))
    n = len(xy)
    return ObjectArray(ids=np.arange(1, n + 1) if ids is None else np.asarray(ids), cls=np.ones(n, int), xy=xy,
                       z=np.full(n, 0.75), lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=np.zeros(n),
                       vxy=np.zeros((n, 2)) if vxy is None else np.atleast_2d(vxy))


def synced_pipeline(**cfg) -> ObuPipeline:
    p = ObuPipeline(ObuPipelineConfig(**{"fusion": "iou-merge", **cfg}))
    req = p.make_time_request(T0)
    p.on_time_reply(answer_time_request(req, "rsu1", T0 + 5_000_000 + THETA, T0 + 5_000_000 + THETA), T0 + 10_000_000)
    return p


def rsu_list(capture_obu_ns, xy, vxy, seq=0):
    header = ObjectListHeader(rsu_id="rsu1", seq=seq, capture_time_ns=capture_obu_ns + THETA,
                              publish_time_ns=capture_obu_ns + THETA + 100_000_000)
    return ObjectList(header=header, objects=states_from_objects(objs(xy, vxy)))


def test_rsu_object_is_compensated_transformed_and_merged():
    p = synced_pipeline()
    cycle = T0 + 1_000_000_000
    p.on_pose(cycle, Pose2D(5.25, -14.0, np.pi / 2))  # facing north
    # RSU saw the runner 150 ms before the cycle at (-40, -5.25) moving east at 14 m/s
    p.on_rsu_message(rsu_list(cycle - 150_000_000, [-40.0, -5.25], [14.0, 0.0]), cycle - 30_000_000)
    p.on_detections(objs([[8.0, 0.0]]), cycle)  # own LiDAR: the van ahead
    out = p.fuse(cycle + 60_000_000)
    assert out.mode == "intra" and len(out.objects) == 2  # the frame of the cycle's slot was there
    rsu = [o for o in out.objects if o.sources == SOURCE_RSU][0]
    # map (-40 + 14 * 0.15, -5.25) seen from (5.25, -14) facing north: ahead = dy, left = -dx
    assert rsu.x == pytest.approx(-5.25 + 14.0, abs=0.02)
    assert rsu.y == pytest.approx(5.25 + 40.0 - 14.0 * 0.15, abs=0.02)
    assert rsu.vy == pytest.approx(-14.0, abs=0.02)  # eastward = to the ego's right
    assert [o.sources for o in out.objects].count(SOURCE_VEHICLE) == 1


def test_duplicate_rsu_object_is_dropped_by_iou_merge():
    p = synced_pipeline()
    cycle = T0 + 1_000_000_000
    p.on_pose(cycle, Pose2D(0.0, 0.0, 0.0))
    p.on_rsu_message(rsu_list(cycle - 100_000_000, [10.2, 0.1], [0.0, 0.0]), cycle)
    p.on_detections(objs([[10.0, 0.0]]), cycle)
    out = p.fuse(cycle)
    assert [o.sources for o in out.objects] == [SOURCE_VEHICLE]


def test_without_sync_or_with_stale_data_it_publishes_vehicle_only():
    p = ObuPipeline(ObuPipelineConfig(fusion="iou-merge"))
    cycle = T0 + 1_000_000_000
    p.on_rsu_message(rsu_list(cycle, [10.0, 0.0], [0, 0]), cycle)
    p.on_detections(objs([[30.0, 0.0]]), cycle)
    assert p.fuse(cycle).mode == "vehicle-only"  # no clock relation yet
    q = synced_pipeline()
    q.on_rsu_message(rsu_list(cycle - 700_000_000, [10.0, 0.0], [0, 0]), cycle)  # older than inter's 0.6 s
    q.on_detections(objs([[30.0, 0.0]]), cycle)
    out = q.fuse(cycle)
    assert out.mode == "vehicle-only" and len(out.objects) == 1


def test_deadline_misses_are_counted_and_duplicates_rejected():
    p = synced_pipeline(deadline_ms=100)
    cycle = T0 + 1_000_000_000
    msg = rsu_list(cycle, [10.0, 0.0], [0, 0])
    p.on_rsu_message(msg, cycle)
    p.on_rsu_message(msg, cycle)
    p.on_detections(objs(np.zeros((0, 2))), cycle)
    p.fuse(cycle + 99 * MS)
    p.on_detections(objs(np.zeros((0, 2))), cycle + 100 * MS)
    p.fuse(cycle + 201 * MS)  # 101 ms after its capture
    m = p.metrics(cycle + 300 * MS)
    assert (m.cycles, m.output_deadline_misses, m.rejected["duplicate"]) == (2, 1, 1)
    assert m.rsus[0].clock_offset_ns == THETA
    p.on_detections(objs(np.zeros((0, 2))), cycle + 500 * MS)
    p.fuse(cycle + 560 * MS)  # on time for its cycle, but 359 ms after the previous output
    assert p.metrics(cycle + 600 * MS).output_deadline_misses == 2


def test_unmatched_time_reply_is_rejected():
    p = ObuPipeline()
    p.make_time_request(T0)
    from schemas.messages import TimeReply

    p.on_time_reply(TimeReply(rsu_id="rsu1", seq=99, t1_ns=T0, t2_ns=T0, t3_ns=T0), T0 + 1)
    assert p.rejected["time_reply_unmatched"] == 1
    assert p.clock_offset("rsu1") is None


def five_hz(p: ObuPipeline, first_capture_ns: int, frames: int, latency_ns: int = 125 * MS) -> int:
    """Feed RSU frames captured every 200 ms, each arriving latency_ns after capture; last capture."""
    for k in range(frames):
        capture = first_capture_ns + k * 200 * MS
        p.on_rsu_message(rsu_list(capture, [10.0 + k, 30.0], [5.0, 0.0], seq=k), capture + latency_ns)
    return first_capture_ns + (frames - 1) * 200 * MS


def test_intra_waits_for_the_slot_frame_and_publishes_when_it_comes():
    p = synced_pipeline(fusion_mode="intra")
    last = five_hz(p, T0 + 1_000_000_000, 5)
    cycle = last + 200 * MS + 10 * MS  # the next frame (captured 10 ms before the cycle) is in flight
    fuse_by = p.on_detections(objs([[8.0, 0.0]]), cycle)
    assert fuse_by == cycle + 90 * MS  # deadline 100 ms - compute margin 10 ms
    assert not p.ready(cycle + 50 * MS)
    p.on_rsu_message(rsu_list(last + 200 * MS, [15.0, 30.0], [5.0, 0.0], seq=5), cycle + 70 * MS)
    assert p.ready(cycle + 70 * MS)
    out = p.fuse(cycle + 70 * MS)
    assert out.mode == "intra" and SOURCE_RSU in [o.sources for o in out.objects]


def test_intra_that_misses_the_window_publishes_on_time_without_rsu_data():
    p = synced_pipeline(fusion_mode="intra")
    last = five_hz(p, T0 + 1_000_000_000, 5)
    cycle = last + 200 * MS + 10 * MS
    fuse_by = p.on_detections(objs([[8.0, 0.0]]), cycle)
    assert not p.ready(fuse_by - 1) and p.ready(fuse_by)
    out = p.fuse(fuse_by)
    assert out.mode == "vehicle-only" and [o.sources for o in out.objects] == [SOURCE_VEHICLE]
    m = p.metrics(fuse_by)
    assert (m.rsu_deadline_misses, m.covered_cycles, m.output_deadline_misses) == (1, 1, 0)


def test_adaptive_does_not_wait_for_a_frame_the_link_cannot_deliver_in_time():
    p = synced_pipeline()  # adaptive
    last = five_hz(p, T0 + 1_000_000_000, 5, latency_ns=160 * MS)  # every frame arrives 160 ms after capture
    cycle = last + 200 * MS + 10 * MS  # its slot frame would need to arrive within 90 ms
    p.on_detections(objs([[8.0, 0.0]]), cycle)
    assert p.ready(cycle + 50 * MS)  # no wait: inter with the buffered frame
    out = p.fuse(cycle + 50 * MS)
    assert out.mode == "inter" and p.metrics(cycle).rsu_deadline_misses == 0


def test_adaptive_waits_when_the_link_is_fast_and_falls_back_to_inter_if_the_frame_is_late():
    p = synced_pipeline()
    last = five_hz(p, T0 + 1_000_000_000, 5, latency_ns=40 * MS)
    cycle = last + 200 * MS + 10 * MS
    fuse_by = p.on_detections(objs([[8.0, 0.0]]), cycle)
    assert not p.ready(cycle + 50 * MS)  # worth waiting: frames arrive 40 ms after capture
    out = p.fuse(fuse_by)  # ... but this one did not
    assert out.mode == "inter" and p.metrics(fuse_by).rsu_deadline_misses == 0


def predictions(t0_obu_ns: int, xy, vxy, steps: int = 50) -> PredictionList:
    header = ObjectListHeader(rsu_id="rsu1", seq=0, capture_time_ns=t0_obu_ns + THETA,
                              publish_time_ns=t0_obu_ns + THETA + 100 * MS)
    k = np.arange(1, steps + 1) * 0.1
    path = PredictedPath(id=1, x=(xy[0] + vxy[0] * k).tolist(), y=(xy[1] + vxy[1] * k).tolist(), yaw=[0.0] * steps)
    return PredictionList(header=header, objects=states_from_objects(objs([xy], [vxy])), paths=(path,))


def test_planning_hands_over_the_rsu_paths_when_tracking_data_is_too_old():
    p = synced_pipeline()
    cycle = T0 + 10_000_000_000
    p.on_pose(cycle, Pose2D(0.0, 0.0, 0.0))
    p.on_rsu_message(rsu_list(cycle - 2_000_000_000, [-40.0, 0.0], [10.0, 0.0]), cycle - 1_800_000_000)
    p.on_predictions(predictions(cycle - 2_000_000_000, [-40.0, 0.0], [10.0, 0.0]), cycle - 1_800_000_000)
    p.on_detections(objs([[8.0, 5.0]]), cycle)
    out = p.fuse(cycle + 50 * MS)
    assert out.mode == "planning"
    rsu = [o for o in out.objects if o.sources == SOURCE_RSU][0]
    assert (rsu.x, rsu.y) == pytest.approx((-20.0, 0.0), abs=0.02)  # 2 s along its path
    assert p.last_planning is not None and p.last_planning.header.capture_time_ns == cycle - 2_000_000_000
    p.on_detections(objs([[8.0, 5.0]]), cycle + 6_000_000_000)  # past the 5 s the paths are good for
    assert p.fuse(cycle + 6_050_000_000).mode == "vehicle-only" and p.last_planning is None


def test_data_stamped_in_the_future_is_refused_and_does_not_shadow_later_data():
    p = synced_pipeline()
    now = T0 + 10_000_000_000
    p.on_predictions(predictions(now + 3_600_000_000_000, [0.0, 0.0], [1.0, 0.0]), now)  # an hour ahead
    p.on_rsu_message(rsu_list(now + 5_000_000_000, [0.0, 0.0], [0.0, 0.0], seq=9), now)
    assert p.rejected["future_timestamp"] == 2
    p.on_predictions(predictions(now - 100 * MS, [0.0, 0.0], [1.0, 0.0]), now)
    p.on_detections(objs([[8.0, 5.0]]), now)
    assert p.fuse(now + 50 * MS).mode == "planning"  # the honest paths were kept
