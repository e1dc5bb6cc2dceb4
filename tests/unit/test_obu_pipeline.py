import numpy as np
import pytest

from fusion.frames import Pose2D
from fusion.objects import ObjectArray
from fusion.wire import states_from_objects
from obu_service.pipeline import ObuPipeline, ObuPipelineConfig
from rsu_service.pipeline import answer_time_request
from schemas.messages import SOURCE_RSU, SOURCE_VEHICLE, ObjectList, ObjectListHeader

T0 = 1_767_225_600 * 10**9
THETA = 350_000_000  # rsu clock - obu clock


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
    assert out.mode == "inter" and len(out.objects) == 2
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
    q = synced_pipeline(max_rsu_age_s=1.0)
    q.on_rsu_message(rsu_list(cycle - 1_500_000_000, [10.0, 0.0], [0, 0]), cycle)
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
    p.fuse(cycle + 99_000_000)
    p.fuse(cycle + 101_000_000)
    m = p.metrics(cycle + 200_000_000)
    assert (m.cycles, m.output_deadline_misses, m.rejected["duplicate"]) == (2, 1, 1)
    assert m.rsus[0].clock_offset_ns == THETA


def test_unmatched_time_reply_is_rejected():
    p = ObuPipeline()
    p.make_time_request(T0)
    from schemas.messages import TimeReply

    p.on_time_reply(TimeReply(rsu_id="rsu1", seq=99, t1_ns=T0, t2_ns=T0, t3_ns=T0), T0 + 1)
    assert p.rejected["time_reply_unmatched"] == 1
    assert p.clock_offset("rsu1") is None
