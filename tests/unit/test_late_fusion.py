import numpy as np
import pytest

from v2i.fusion.nms import nms_fuse
from v2i.core.objects import ObjectArray
from v2i.fusion.tclf import tclf_compensate, tclf_fuse, two_frame_velocity
from schemas.messages import SOURCE_RSU, SOURCE_VEHICLE


def objs(xy, conf=None, src=SOURCE_VEHICLE, cls=1):
    xy = np.atleast_2d(np.asarray(xy, float))
    n = len(xy)
    return ObjectArray(ids=np.arange(n), cls=np.full(n, cls), xy=xy, z=np.zeros(n), lwh=np.tile([4.5, 1.8, 1.5], (n, 1)),
                       yaw=np.zeros(n), vxy=np.zeros((n, 2)),
                       confidence=np.ones(n) if conf is None else np.asarray(conf, float), sources=np.full(n, src))


def test_nms_keeps_the_most_confident_and_records_both_sources():
    own = objs([[0, 0], [20, 0]], conf=[0.6, 0.9])
    rsu = objs([[0.3, 0.0], [50, 0]], conf=[0.8, 0.7], src=SOURCE_RSU)
    out = nms_fuse(own, rsu, iou_threshold=0.1)
    assert len(out) == 3
    kept = out.take(np.argmin(np.abs(out.xy[:, 0] - 0.15)))
    assert kept.xy[0, 0] == pytest.approx(0.3)  # the RSU box had the higher confidence
    assert kept.sources[0] == SOURCE_VEHICLE | SOURCE_RSU


def test_two_frame_velocity_and_linear_extrapolation():
    prev = objs([[0, 0], [100, 5]], src=SOURCE_RSU)
    curr = objs([[2.8, 0], [100, 5], [60, 60]], src=SOURCE_RSU)
    v = two_frame_velocity(prev, curr, dt_s=0.2)
    np.testing.assert_allclose(v, [[14.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    moved = tclf_compensate(prev, curr, frame_dt_s=0.2, latency_s=0.15)
    np.testing.assert_allclose(moved.xy[0], [2.8 + 14.0 * 0.15, 0.0])


def test_tclf_merges_matched_pairs_by_confidence():
    own = objs([[10, 0]], conf=[0.75])
    rsu = objs([[11, 0], [40, 3]], conf=[0.25, 0.5], src=SOURCE_RSU)
    out = tclf_fuse(own, rsu, gate_m=3.0)
    assert len(out) == 2
    np.testing.assert_allclose(out.xy[0], [10.25, 0.0])
    assert out.sources.tolist() == [SOURCE_VEHICLE | SOURCE_RSU, SOURCE_RSU]
