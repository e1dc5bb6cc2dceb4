"""Which RSUs a cycle's output used (``ObuPipeline.last_rsu_inputs``) and mode gating by clock uncertainty."""

import numpy as np

from v2i.core.frames import Pose2D
from obu_service.pipeline import ObuPipeline, ObuPipelineConfig
from test_obu_pipeline import T0, objs, predictions, rsu_list, synced_pipeline


def test_last_rsu_inputs_names_the_rsus_a_cycle_fused():
    p = synced_pipeline(fusion="kf")
    cycle = T0 + 1_000_000_000
    p.on_pose(cycle, Pose2D(0.0, 0.0, 0.0))
    p.on_rsu_message(rsu_list(cycle - 100_000_000, [10.0, 0.0], [0, 0]), cycle - 20_000_000)
    p.on_detections(objs([[30.0, 0.0]]), cycle)
    out = p.fuse(cycle)
    assert out.mode in ("intra", "inter") and p.last_rsu_inputs == ("rsu1",)
    cycle += 100_000_000
    p.on_detections(objs([[30.0, 0.0]]), cycle)
    p.fuse(cycle)
    assert p.last_rsu_inputs == ()  # kf: the frame was fed to the tracker once, nothing new this cycle
