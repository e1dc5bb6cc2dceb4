"""ObuPipeline keeps what on_detections and ready asked ModeInputs for the cycle, and fuse asks again only if an
input came in since (``_asked``, keyed by ``_inputs_version``)."""

import numpy as np
import pytest

from v2i.core.frames import Pose2D
from obu_service.pipeline import ObuPipeline
from schemas.messages import SOURCE_RSU
from rsu_service.pipeline import answer_time_request
from test_obu_pipeline import T0, THETA, objs, rsu_list, synced_pipeline


def _rsu_xy(out):
    return sorted((round(o.x, 6), round(o.y, 6)) for o in out.objects if o.sources == SOURCE_RSU)


@pytest.mark.parametrize("mode", ["inter", "adaptive"])
def test_fuse_sees_a_list_that_came_after_on_detections(mode, monkeypatch):
    """An RSU list received between on_detections and fuse is fused (inter: the newest frame), exactly as by a
    pipeline that asks ModeInputs at fuse time, and the answers kept from on_detections are not used."""
    outs = []
    for keep in (True, False):
        p = synced_pipeline(fusion_mode=mode)
        if not keep:
            monkeypatch.setattr(p, "_asked", lambda cycle, what, ask: ask())
        cycle = T0 + 1_000_000_000
        p.on_pose(cycle, Pose2D(0.0, 0.0, 0.0))
        p.on_rsu_message(rsu_list(cycle - 300_000_000, [40.0, 10.0], [0.0, 0.0], seq=0), cycle - 200_000_000)
        p.on_detections(objs([[8.0, 0.0]]), cycle)
        p.on_rsu_message(rsu_list(cycle - 20_000_000, [40.0, -10.0], [0.0, 0.0], seq=1), cycle + 5_000_000)
        outs.append(p.fuse(cycle + 10_000_000))
    assert (40.0, -10.0) in _rsu_xy(outs[0])  # the list that came after on_detections
    assert _rsu_xy(outs[0]) == _rsu_xy(outs[1]) and outs[0].mode == outs[1].mode


def test_fuse_reuses_the_answers_when_nothing_came_in(monkeypatch):
    p = synced_pipeline(fusion_mode="inter")
    cycle = T0 + 1_000_000_000
    p.on_pose(cycle, Pose2D(0.0, 0.0, 0.0))
    p.on_rsu_message(rsu_list(cycle - 150_000_000, [40.0, 10.0], [0.0, 0.0]), cycle - 50_000_000)
    p.on_detections(objs([[8.0, 0.0]]), cycle)
    asked = []
    for name in ("inter", "planning"):
        ask = getattr(p._inputs, name)
        monkeypatch.setattr(p._inputs, name, lambda *a, _ask=ask, _n=name: asked.append(_n) or _ask(*a))
    out = p.fuse(cycle)
    assert asked == [] and _rsu_xy(out) == [(40.0, 10.0)]
    p.on_detections(objs([[8.0, 0.0]]), cycle + 100_000_000)  # (asked here: the new cycle's answers)
    t1 = cycle + 100_000_000
    reply = answer_time_request(p.make_time_request(t1), "rsu1", t1 + 500_000 + THETA, t1 + 500_000 + THETA)
    p.on_time_reply(reply, t1 + 1_000_000)  # an input: asked again
    asked.clear()
    p.fuse(cycle + 100_000_000)
    assert asked == ["inter", "planning"]
