"""A confirmed RSU clock step keeps the RSU's lists (placed by the clock that stamped them) and its tracks."""

import numpy as np
import pytest

from v2i.core.frames import Pose2D
from v2i.fusion.wire import states_from_objects
from obu_service.pipeline import ObuPipeline, ObuPipelineConfig
from obu_service.rsu_table import RsuState
from v2i.clock.clock_sync import ConfirmedStep, OffsetEstimate
from rsu_service.pipeline import answer_time_request
from schemas.messages import ObjectList, ObjectListHeader
from test_obu_pipeline import MS, T0, THETA, objs

STEP_AT_NS = T0 + 6_000 * MS  # OBU (true) time of the RSU clock step
SPEED_MPS = 10.0  # the target, seen by the RSU alone, drives east at this speed from x = -60 m


def target_x_m(t_ns: int) -> float:
    return -60.0 + SPEED_MPS * (t_ns - T0) * 1e-9


def rsu_clock_ns(t_ns: int, step_ns: int) -> int:
    """The RSU's clock reading at OBU (true) time t: THETA ahead, stepped by step_ns at STEP_AT_NS."""
    return t_ns + THETA + (step_ns if t_ns >= STEP_AT_NS else 0)


def events(step_ns: int, end_ns: int, list_latency_ns: int = 60 * MS):
    """(OBU time, order, kind, payload) of a run: time exchanges at 10 Hz (5 ms each way), RSU lists at
    5 Hz (arriving list_latency_ns after capture), own cycles at 10 Hz (fused 50 ms after capture)."""
    out = []
    for k in range((end_ns - T0) // (100 * MS)):
        t = T0 + k * 100 * MS
        out.append((t + 3 * MS, 0, "time", t + 3 * MS))
        out.append((t, 2, "cycle", t))
        if k % 2 == 0:
            capture = t - 10 * MS
            out.append((capture + list_latency_ns, 1, "list", (capture, k // 2)))
    return sorted(out)


def run(step_ms: float, end_ns: int = T0 + 9_000 * MS, **config):
    """The pipeline through a run with an RSU clock step of step_ms; (pipeline, [(cycle, output)])."""
    step_ns = round(step_ms * MS)
    p = ObuPipeline(ObuPipelineConfig(**{"fusion": "kf", **config}))
    outputs = []
    for t, _, kind, payload in events(step_ns, end_ns):
        if kind == "time":
            req = p.make_time_request(payload)
            at_rsu = rsu_clock_ns(payload + 5 * MS, step_ns)
            p.on_time_reply(answer_time_request(req, "rsu1", at_rsu, at_rsu), payload + 10 * MS)
        elif kind == "list":
            capture, seq = payload
            stamp = rsu_clock_ns(capture, step_ns)
            header = ObjectListHeader(rsu_id="rsu1", seq=seq, capture_time_ns=stamp, publish_time_ns=stamp + 20 * MS)
            target = objs([[target_x_m(capture), 30.0]], [[SPEED_MPS, 0.0]], ids=[7])
            p.on_rsu_message(ObjectList(header=header, objects=states_from_objects(target)), t)
        else:
            p.on_pose(t, Pose2D(0.0, 0.0, 0.0))
            p.on_detections(objs([[8.0, -3.0]]), t)
            outputs.append((t, p.fuse(t + 50 * MS)))
    return p, outputs


def target_ids(outputs, since_ns: int) -> list[int | None]:
    """The id of the output object on the target (within 3 m of it) per cycle since ``since_ns``."""
    ids = []
    for t, out in outputs:
        if t < since_ns:
            continue
        near = [o.id for o in out.objects if np.hypot(o.x - target_x_m(t), o.y - 30.0) < 3.0]
        ids.append(near[0] if near else None)
    return ids


@pytest.mark.parametrize("step_ms", [-700.0, 700.0, -5000.0])
def test_a_confirmed_step_keeps_the_lists_and_the_track(step_ms):
    p, outputs = run(step_ms)
    metrics = p.metrics(outputs[-1][0])
    assert p.clock_offset("rsu1").steps == 1 == metrics.rsus[0].clock_steps  # the filter confirmed the step
    assert metrics.rsu_inputs in ((), ("rsu1",))  # (kf: the RSU's list is fed every other cycle)
    ids = target_ids(outputs, T0 + 4_000 * MS)
    assert None not in ids and len(set(ids)) == 1  # one track throughout: no gap, no new id
    assert p.rejected["stale_after_clock_step"] <= 1  # only a list stamped inside the step's window
    assert p.mode_reasons["clock_uncertainty"] >= 1  # while the step was suspected, the RSU was not fused


def test_lists_stamped_before_the_step_are_placed_by_the_old_clock():
    p, _ = run(-700.0, end_ns=STEP_AT_NS + 1_000 * MS)
    state = p._rsus.get("rsu1")
    placed = p._inputs.placed(state, STEP_AT_NS + 1_000 * MS)
    for raw, frame in placed:  # each at its true capture time (the lists are captured at t - 10 ms, t in 100 ms)
        assert (frame.capture_ns - T0 + 10 * MS) % (100 * MS) == pytest.approx(0, abs=2 * MS)
    assert any(raw.clock is not None for raw, _ in placed)  # some were stamped before the step
    assert [f.capture_ns for _, f in placed] == sorted(f.capture_ns for _, f in placed)


class _Sync:
    """A clock filter that has confirmed a step of step_ns at OBU time STEP_AT_NS (seen between
    after_ns and before_ns): ``RsuState.clock_of`` reads only these two."""

    def __init__(self, step_ns: int, after_ns: int, before_ns: int):
        self.old = OffsetEstimate(THETA, 5 * MS, 100, at_ns=STEP_AT_NS)
        self.new = OffsetEstimate(THETA + step_ns, 5 * MS, 100, at_ns=STEP_AT_NS, steps=1)
        self.last_step = ConfirmedStep(1, after_ns, before_ns, self.old)

    def estimate_at(self, t_ns: int) -> OffsetEstimate:
        return self.new


def state_after_step(step_ms: float, latency_ms: float | None) -> RsuState:
    state = RsuState("rsu1", 0, True, T0, sync=_Sync(round(step_ms * MS), STEP_AT_NS - 50 * MS, STEP_AT_NS + 150 * MS))
    if latency_ms is not None:  # the link's measured capture-to-arrival latency
        for k in range(20):
            t = T0 + k * 200 * MS
            state.monitor.on_message(k, t, t + 10 * MS, t + round(latency_ms * MS), True)
    return state


@pytest.mark.parametrize("step_ms", [-700.0, 700.0])
def test_clock_of_names_the_clock_that_read_a_stamp(step_ms):
    state = state_after_step(step_ms, latency_ms=60.0)
    slack_ns = 25 * MS
    for capture_ns, which in ((STEP_AT_NS - 300 * MS, "old"), (STEP_AT_NS - 20 * MS, "old"),
                              (STEP_AT_NS + 20 * MS, "current"), (STEP_AT_NS + 300 * MS, "current")):
        read = state.sync.old if which == "old" else state.sync.new
        clock, got = state.clock_of(read.to_rsu_ns(capture_ns), capture_ns + 60 * MS, slack_ns)
        assert got == which and clock.to_obu_ns(read.to_rsu_ns(capture_ns)) == capture_ns


def test_a_stamp_either_clock_could_have_read_is_ambiguous():
    # -700 ms: a list stamped just after the step reads as one captured 700 ms earlier by the old clock;
    # a link that takes up to a second makes both latencies plausible
    state = state_after_step(-700.0, latency_ms=1000.0)
    capture_ns = STEP_AT_NS + 100 * MS
    assert state.clock_of(state.sync.new.to_rsu_ns(capture_ns), capture_ns + 60 * MS, 25 * MS) == (None, "ambiguous")
    unmeasured = state_after_step(-700.0, latency_ms=None)  # and so does a link not measured yet
    assert unmeasured.clock_of(state.sync.new.to_rsu_ns(capture_ns), capture_ns + 60 * MS, 25 * MS)[1] == "ambiguous"
    # a step smaller than the slack: either clock places it within the slack, the current one is taken
    small = state_after_step(-10.0, latency_ms=None)
    assert small.clock_of(small.sync.new.to_rsu_ns(capture_ns), capture_ns + 60 * MS, 25 * MS)[1] == "current"
