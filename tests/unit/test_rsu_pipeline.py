"""The RSU pipeline runs on its monotonic clock: wall-clock steps move stamps, never the tracker."""

import numpy as np
import pytest

from v2i.core.objects import ObjectArray
from rsu_service.pipeline import RsuPipeline, RsuPipelineConfig, Stamp

T0 = 1_767_225_600 * 10**9
PERIOD_NS = 200_000_000


def car_at(x_m: float) -> ObjectArray:
    return ObjectArray(ids=np.array([-1]), cls=np.array([1]), xy=np.array([[x_m, 0.0]]), z=np.zeros(1),
                       lwh=np.array([[4.5, 1.8, 1.5]]), yaw=np.zeros(1), vxy=np.zeros((1, 2)),
                       cov_xy=np.eye(2)[None] * 0.01)


@pytest.mark.parametrize("step_ms", [-2000, -700, -210, -1, 1, 500, 2000])
@pytest.mark.parametrize("predict_ahead", [False, True])
def test_wall_clock_steps_of_either_sign_keep_the_rsu_tracking(step_ms, predict_ahead):
    """A car at 14 m/s seen at 5 Hz; the wall clock steps by step_ms after frame 5. The RSU
    keeps one track with the right speed, stamps the wire with the stepped wall clock, and
    predicts ahead by the monotonic processing time (not by the step)."""
    rsu = RsuPipeline(RsuPipelineConfig(predict_ahead=predict_ahead))
    step_ns = step_ms * 1_000_000
    for k in range(12):
        mono = T0 + k * PERIOD_NS
        wall = mono + (step_ns if k >= 5 else 0)
        msg = rsu.on_frame(car_at(14.0 * k * 0.2), Stamp(wall, mono), Stamp(wall + 100_000_000, mono + 100_000_000))
        assert msg.header.capture_time_ns == wall
        assert msg.header.publish_time_ns == wall + 100_000_000
        assert msg.header.prediction_ns == (100_000_000 if predict_ahead else 0)
    assert [o.id for o in msg.objects] == [1]  # one track all along
    assert msg.objects[0].vx == pytest.approx(14.0, abs=0.5)
    pred = rsu.predictions(Stamp(wall + 120_000_000, mono + 120_000_000))
    assert pred.header.capture_time_ns == wall and [o.id for o in pred.objects] == [1]


def test_a_step_between_capture_and_publish_never_stamps_publish_before_capture():
    rsu = RsuPipeline(RsuPipelineConfig(predict_ahead=True))
    msg = rsu.on_frame(car_at(0.0), Stamp(T0, T0), Stamp(T0 - 700_000_000, T0 + 100_000_000))
    assert msg.header.publish_time_ns == msg.header.capture_time_ns == T0
    assert msg.header.prediction_ns == 100_000_000  # the monotonic time between them
    up = rsu.upsampled(Stamp(T0 - 600_000_000, T0 + 200_000_000))
    assert up.header.prediction_ns == 200_000_000


def test_a_far_camera_track_fits_the_wire():
    """A camera car 300 m out (variance 400 m^2, as a 15 m pole sees it): the two-point
    velocity variance (s1^2 + s2^2) / dt^2 = 8e4 passes the wire's 1e4 bound. The RSU clips it
    (counted) instead of failing to build its list (it did: 'cov_vxx <= 10000')."""
    rsu = RsuPipeline(RsuPipelineConfig())
    far = lambda x: ObjectArray(ids=np.array([-1]), cls=np.array([1]), xy=np.array([[x, 0.0]]), z=np.zeros(1),  # noqa: E731
                                lwh=np.array([[4.5, 1.8, 1.5]]), yaw=np.zeros(1), vxy=np.zeros((1, 2)),
                                cov_xy=np.eye(2)[None] * 400.0)
    for k in range(6):
        msg = rsu.on_frame(far(300.0 + 3.0 * k), T0 + k * 100_000_000, T0 + k * 100_000_000 + 50_000_000)
        assert rsu.predictions(T0 + k * 100_000_000 + 60_000_000) is not None
    assert msg.objects and all(o.cov_vxx <= 1e4 for o in msg.objects)
    assert rsu.wire_fixes["clipped"] > 0


@pytest.mark.parametrize("predict_ahead", [False, True])
def test_predictions_carry_the_frames_tracks_as_the_list_does(predict_ahead):
    """A frame's tracks are fitted to the wire once: the prediction list carries the tracks at
    capture (t0), equal to the object list's without predict_ahead; with it the list's objects
    are those tracks predicted to the publish time (a car at 14 m/s moves 1.4 m in 100 ms)."""
    rsu = RsuPipeline(RsuPipelineConfig(predict_ahead=predict_ahead))
    for k in range(8):
        t = T0 + k * PERIOD_NS
        msg = rsu.on_frame(car_at(14.0 * k * 0.2), t, t + 100_000_000)
    pred = rsu.predictions(t + 120_000_000)
    assert len(pred.objects) == len(msg.objects) == 1
    if predict_ahead:
        assert msg.objects[0].x - pred.objects[0].x == pytest.approx(1.4, abs=0.1)
    else:
        assert np.array_equal(msg.objects.codes, pred.objects.codes)
    assert pred.objects[0].x == pytest.approx(14.0 * 7 * 0.2, abs=0.2)
