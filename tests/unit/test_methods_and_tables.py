import numpy as np
import pytest

from v2i.offline.tables import dropout_profile, fixed_delay_profile, to_markdown, _stats
from v2i.core.objects import ObjectArray
from link_emulator.channel import Channel
from link_emulator.profile import load_profile
from obu_service.config import ObuConfig
from obu_service.methods import make_fusion
from rsu_service.pipeline import RsuPipeline, RsuPipelineConfig

T0 = 1_767_225_600 * 10**9


def test_oosm_requires_a_filter():
    with pytest.raises(ValueError, match="oosm"):
        make_fusion("nms", "oosm")
    with pytest.raises(ValueError):
        ObuConfig(fusion="iou-merge", compensation="oosm")
    make_fusion("kf", "oosm")
    with pytest.raises(ValueError, match="fusion"):
        make_fusion("magic", "predict")


def test_rsu_track_predict_publishes_ahead_and_upsamples():
    rsu = RsuPipeline(RsuPipelineConfig(predict_ahead=True))
    for k in range(4):
        t = T0 + k * 200_000_000
        det = ObjectArray(ids=np.array([-1]), cls=np.array([1]), xy=np.array([[14.0 * k * 0.2, 0.0]]), z=np.zeros(1),
                          lwh=np.array([[4.5, 1.8, 1.5]]), yaw=np.zeros(1), vxy=np.zeros((1, 2)),
                          cov_xy=np.eye(2)[None] * 0.01)
        first = rsu.on_frame(det, t, t + 100_000_000)
    second = rsu.upsampled(t + 200_000_000)
    assert first.header.prediction_ns == 100_000_000 and second.header.prediction_ns == 200_000_000
    assert second.header.seq == first.header.seq + 1
    # the second list is the same track 100 ms further along: dx = v * 0.1 s
    dx = second.objects[0].x - first.objects[0].x
    assert dx == pytest.approx(first.objects[0].vx * 0.1, abs=0.02)
    assert RsuPipeline().upsampled(T0) is None  # without track-predict nothing is upsampled


def test_generated_robustness_profiles():
    fixed = fixed_delay_profile(300, 600)
    ch = Channel(fixed.downlink, np.random.default_rng(0))
    delays = np.array([ch.transmit(T0, 1000) - T0 for _ in range(2000)]) / 1e6
    assert delays.min() >= 300 and delays.max() < 600
    dropped = dropout_profile(load_profile("lte-v2x"), 0.75)
    ch = Channel(dropped.downlink, np.random.default_rng(0))
    lost = np.mean([ch.transmit(T0, 1000) is None for _ in range(4000)])
    assert lost == pytest.approx(0.75, abs=0.03)


def test_table_statistics_and_markdown():
    s = _stats([1.0, None, 3.0])
    assert (s["mean"], s["std"], s["n"]) == (2.0, 1.0, 2)
    md = to_markdown([{"title": "T", "source": "S", "columns": ["mAP"], "rows": [{"label": "kf", "mAP": s}]}], [1, 2])
    assert "| kf | 2.000 +- 1.000 (n=2) |" in md


def test_lane_compensation_needs_a_map_and_follows_the_lane(tmp_path):
    from obu_service.methods import RsuFrame, compensate
    from rsu_service.prediction import make_predictor
    from v2i.sim.maps import lane_predictor
    from v2i.sim.scenario_site import scenario_site

    with pytest.raises(ValueError, match="Lanelet2"):
        make_fusion("kf", "lane")
    site = scenario_site("red-light-runner").model_copy(update={"map": None})  # a site with no map
    with pytest.raises(ValueError, match="Lanelet2 map"):
        ObuConfig(compensation="lane").lanes(site)
    with pytest.raises(ValueError, match="Lanelet2 map"):
        make_predictor("lane", site)
    lanes = lane_predictor("red-light-runner")
    make_fusion("kf", "lane", lanes=lanes)
    # an eastbound car in the inner lane moves along it: same as constant velocity on a straight lane
    car = ObjectArray(ids=np.array([7]), cls=np.array([1]), xy=np.array([[-40.0, -1.75]]), z=np.zeros(1),
                      lwh=np.array([[4.5, 1.8, 1.5]]), yaw=np.zeros(1), vxy=np.array([[13.9, 0.0]]),
                      cov_xy=np.eye(2)[None] * 0.01)
    frame = RsuFrame(0, 0, T0, T0, car)
    moved = compensate(frame, T0 + 500_000_000, "lane", lanes.predict_objects)
    assert moved.xy[0] == pytest.approx([-40.0 + 13.9 * 0.5, -1.75], abs=1e-6)


def test_rsu_predictions_carry_one_path_per_track():
    rsu = RsuPipeline(RsuPipelineConfig(horizon_s=2.0, path_step_s=0.5))
    assert rsu.predictions(T0) is None
    det = ObjectArray(ids=np.array([-1]), cls=np.array([1]), xy=np.array([[0.0, 0.0]]), z=np.zeros(1),
                      lwh=np.array([[4.5, 1.8, 1.5]]), yaw=np.zeros(1), vxy=np.zeros((1, 2)),
                      cov_xy=np.eye(2)[None] * 0.01)
    for k in range(4):
        rsu.on_frame(det, T0 + k * 200_000_000, T0 + k * 200_000_000 + 100_000_000)
    pred = rsu.predictions(T0 + 700_000_000)
    assert len(pred.paths) == len(pred.objects) >= 1
    assert len(pred.paths[0].x) == 4 and pred.step_ns == 500_000_000 and pred.horizon_ns == 2_000_000_000
    assert pred.header.capture_time_ns == T0 + 600_000_000
