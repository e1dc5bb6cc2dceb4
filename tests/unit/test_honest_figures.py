"""Issue 31, honest figures: step recovery relative to the pre-step error, the step window scored apart,
the clock error of the cycles that fused, every RSU's clock, one id-switch definition, and a
vehicle-only baseline that does not move with the link."""

from __future__ import annotations

import numpy as np
import pytest

from v2i.core.objects import ObjectArray
from v2i.scoring.metrics import (FUSED, PLANNED, CycleFrame, DetectionTally, TargetTally, clock_errors,
                                 recovery_band_ms)
from v2i.sim.clock import ClockStep, DriftingClock, SystemClock

START_NS = 10**18
STEP_NS = START_NS + 10 * 10**9  # the step at 10 s


def _truth(step_ms: float = -700.0, offset_ms: float = 20.0) -> DriftingClock:
    return DriftingClock(SystemClock(), offset_ns=round(offset_ms * 1e6), ref_ns=START_NS,
                         steps=(ClockStep(STEP_NS, round(step_ms * 1e6)),))


def _samples(truth: DriftingClock, bias_ms: float, caught_s: float, end_s: float = 20.0, rsu: int = 0,
             seed: int = 0) -> np.ndarray:
    """10 Hz estimates from 0 s: the truth + bias_ms (+-0.3 ms noise), except from the step until
    caught_s after it, when the estimate still holds the pre-step offset (off by the step)."""
    rng = np.random.default_rng(seed)
    t = START_NS + np.arange(0, round(end_s * 10)) * 100_000_000
    true_ns = np.array([truth.offset_at(int(x)) for x in t], dtype=float)
    before = np.array([truth.offset_at(int(STEP_NS) - 1)] * len(t), dtype=float)
    est = true_ns + (bias_ms + rng.uniform(-0.3, 0.3, len(t))) * 1e6
    lagging = (t >= STEP_NS) & (t < STEP_NS + caught_s * 1e9)
    est[lagging] = before[lagging] + bias_ms * 1e6
    return np.column_stack([t, est, est, np.zeros(len(t)), np.full(len(t), rsu)]).astype(float)


@pytest.mark.parametrize("bias_ms", [15.0, 0.2])  # an asymmetric link (40 / 10 ms: 15 ms bias), a symmetric one
def test_step_recovery_is_measured_against_the_error_before_the_step(bias_ms):
    truth = _truth()
    rows = _samples(truth, bias_ms, caught_s=0.45)
    out = clock_errors(rows, [truth], START_NS, STEP_NS)
    assert out["clock_step_recovery_s"] == pytest.approx(0.5)  # the first 10 Hz sample after 0.45 s
    band = recovery_band_ms(rows[:, 0], np.abs(rows[:, 1] - [truth.offset_at(int(t)) for t in rows[:, 0]]) * 1e-6,
                            STEP_NS)
    assert max(bias_ms, 1.0) * 1.25 - 0.4 < band <= (max(bias_ms, 1.0) + 0.3) * 1.25
    # the 700 ms of the step window are in a figure of their own, the steady state stays the bias
    window = out["clock_offset_error_step_window_ms"]
    assert window["samples"] == 30 and window["max"] == pytest.approx(700 + bias_ms, abs=0.5)
    assert out["clock_offset_error_ms"]["max"] < bias_ms + 0.5


def test_a_run_that_ends_unrecovered_has_no_recovery_time():
    truth = _truth(step_ms=-5000.0)
    out = clock_errors(_samples(truth, 15.0, caught_s=30.0), [truth], START_NS, STEP_NS)
    assert out["clock_step_recovery_s"] is None


def test_every_rsu_is_scored_against_its_own_clock_and_the_slowest_recovery_counts():
    clocks = [_truth(offset_ms=20.0), _truth(offset_ms=-350.0)]
    rows = np.vstack([_samples(clocks[0], 0.2, 0.45, rsu=0), _samples(clocks[1], 0.2, 1.95, rsu=1, seed=1)])
    out = clock_errors(rows, clocks, START_NS, STEP_NS, steps={"a": 1, "b": 1}, rsu_ids=["a", "b"])
    assert out["clock_offset_error_ms"]["max"] < 0.6  # scored against one clock, RSU b would be 370 ms off
    assert out["clock_step_recovery_s"] == pytest.approx(2.0)
    assert out["clock_steps_detected"] == 2 and out["clock_rsus"]["b"]["steps_detected"] == 1
    assert out["clock_rsus"]["a"]["offset_error_ms"]["samples"] == out["clock_rsus"]["b"]["offset_error_ms"]["samples"]


def test_the_clock_error_of_the_cycles_that_used_rsu_data():
    truth = _truth()
    t = STEP_NS - 10**9
    theta = truth.offset_at(t)
    used = [(t, theta + 3e6, 0, FUSED), (t, theta - 8e6, 0, FUSED), (t, theta + 40e6, 0, PLANNED)]
    out = clock_errors(np.zeros((0, 5)), [truth], START_NS, None, used)
    assert out["clock_error_when_fused_max_ms"] == pytest.approx(8.0)
    assert out["clock_error_when_planning_max_ms"] == pytest.approx(40.0)
    none = clock_errors(np.zeros((0, 5)), [truth], START_NS, None)
    assert none["clock_error_when_fused_max_ms"] is None and none["clock_steps_detected"] is None


def _frame(k: int, out_id: int | None, offset_m: float) -> CycleFrame:
    """The target (id 7) 20 m ahead and a bystander (id 8); the output: the bystander's track and, with
    out_id, one object offset_m beside the target."""
    truth = ObjectArray(ids=np.array([7, 8]), cls=np.zeros(2, np.int64), xy=np.array([[20.0, 0.0], [0.0, 30.0]]),
                        z=np.zeros(2), lwh=np.ones((2, 3)), yaw=np.zeros(2), vxy=np.zeros((2, 2)))
    ids, xy = [50], [[0.0, 30.0]]
    if out_id is not None:
        ids, xy = [out_id, *ids], [[20.0 + offset_m, 0.0], *xy]
    n = len(ids)
    out = ObjectArray(ids=np.array(ids), cls=np.zeros(n, np.int64), xy=np.array(xy), z=np.zeros(n),
                      lwh=np.ones((n, 3)), yaw=np.zeros(n), vxy=np.zeros((n, 2)), cov_xy=np.tile(np.eye(2), (n, 1, 1)),
                      sources=np.ones(n, np.int64))
    return CycleFrame(k * 100_000_000, 0.1 * k, truth, out)


def test_target_and_tracking_id_switches_are_one_definition():
    """Id 1 on the target, a 3 m-off ghost under id 2 (inside the 4 m target gate, outside MOT's 2 m),
    then id 1 again: the old count (np.diff of the matched ids) said 2 switches, motmetrics 0; then a
    real change to id 3: one switch in both."""
    frames = [_frame(0, 1, 0.3), _frame(1, 2, 3.0), _frame(2, 1, 0.3), _frame(3, 3, 0.2), _frame(4, 3, 0.2)]
    detection = DetectionTally()
    shared, alone = TargetTally(7, mot=detection.mot), TargetTally(7)
    for frame in frames:
        for tally in (detection, shared, alone):
            tally.add(frame)
    ids = [1, 2, 1, 3, 3]
    assert np.count_nonzero(np.diff(ids)) == 3  # the old target count
    assert shared.score().id_switches == alone.score().id_switches == 1
    assert detection.scores()["tracking"]["id_switches"] == 1
    assert shared.score().track_ids == 3  # the ids it was detected under, as before


def test_the_vehicle_only_baseline_does_not_move_with_the_link_or_the_method():
    """Runs that differ in all but scenario and seed (method, mode, profile, security, chaos) have the same
    vehicle-only figures, and the demo's way (recomputed from scenario, seed, start and cycle times) too."""
    from v2i.offline.baseline import own_baseline
    from v2i.offline.runner import OfflineRun
    from v2i.offline.spec import RunSpec

    from v2i.offline.chaos import ChaosTimeline, with_chaos

    # a link outage from 4 s to the end and an RSU clock step at 3 s
    chaos = ChaosTimeline.model_validate({"name": "dark", "events": [{"at_s": 4, "outage": {"duration_s": 20}},
                                                                      {"at_s": 3, "rsu_clock_step": {"step_ms": 500}}]})
    reports, runs = [], []
    for fusion, mode, profile, security, timeline in (("kf", "adaptive", "lte-v2x", None, None),
                                                      ("iou-merge", "planning", "dsrc", "strict", None),
                                                      ("kf", "inter", "lte-v2x", None, chaos)):
        spec = with_chaos(RunSpec(scenario="red-light-runner", fusion=fusion, fusion_mode=mode, profile=profile,
                                  security=security, seed=2, duration_s=12.0), timeline)
        run = OfflineRun(spec, chaos=timeline)
        run.execute()
        runs.append(run)
        reports.append(run.report())
    assert len({str(r["target"]) for r in reports}) == 3  # the fused outputs differ ...
    assert reports[0]["vehicle_only"] == reports[1]["vehicle_only"] == reports[2]["vehicle_only"]  # ... the baseline not
    assert reports[0]["vehicle_only"]["detected_cycles"] > 0
    record = runs[0].record
    again = own_baseline(record.world, 2, record.start_ns, record.cycle_times_ns)
    assert again.score().as_dict() == reports[0]["vehicle_only"]


def test_eval_scores_every_rsus_clock():
    from v2i.offline.runner import OfflineRun
    from v2i.offline.spec import RunSpec

    run = OfflineRun(RunSpec(scenario="two-rsu-corridor", seed=1, duration_s=8.0, rsu_clock_offset_ms=30.0))
    run.execute()
    report = run.report()
    ids = [r.cfg.id for r in run.rsus]
    assert len(ids) == 2 and set(report["clock_rsus"]) == set(ids)
    for rid in ids:
        assert report["clock_rsus"][rid]["offset_error_ms"]["samples"] > 0
        assert report["clock_rsus"][rid]["offset_error_ms"]["max"] < 5.0
    assert report["clock_steps_detected"] == 0
    assert report["clock_offset_error_ms"]["samples"] == sum(
        report["clock_rsus"][rid]["offset_error_ms"]["samples"] for rid in ids)


def test_the_summary_states_the_clock_when_used_and_the_step():
    from v2i.offline.spec import summary

    seen = {"first_detection_distance_m": 40.0, "mean_bev_iou": 0.7, "rmse_m": 0.5, "detected_cycles": 9,
            "track_ids": 1, "id_switches": 0}
    report = {"scenario": "red-light-runner", "profile": "p", "fusion": "kf", "compensation": "predict",
              "fusion_mode": "adaptive", "seed": 0, "duration_s": 30.0, "cycles": 300, "driver": "eval",
              "target": seen, "vehicle_only": seen, "mode_share": {"intra": 1.0}, "output_deadline_miss_ratio": 0.0,
              "rsu_deadline_miss_ratio": 0.0, "rsu_messages_received": 9, "rsu_perception": {"frames": 0},
              "clock_offset_error_ms": {"p50": 15.0, "p95": 15.0, "max": 15.2}, "clock_offset_error_naive_ms": {"p95": 15.0},
              "clock_drift_error_ppm": 0.1, "displacement_error_m": None, "clock_error_when_fused_max_ms": 15.243,
              "clock_error_when_planning_max_ms": None, "clock_steps_detected": 1,
              "clock_offset_error_step_window_ms": {"p50": 15.0, "p95": 715.0, "max": 715.0, "samples": 30},
              "clock_step_recovery_s": 0.55}
    text = summary(report)
    assert ("clock when used: fused max 15.243 ms, planning max n/a; steps detected 1; step window p95 715.000 ms, "
            "max 715.000 ms; recovered after 0.55 s") in text
    assert "recovered never" in summary({**report, "clock_step_recovery_s": None})


def test_switches_per_truth_id_are_motmetrics_switch_events():
    """MotTally.switches_of (what target.id_switches reads) is motmetrics' SWITCH events per object id."""
    import motmetrics as mm

    from test_detection_metrics import generated_tracks
    from v2i.scoring.detection_metrics import MotTally, _distance_matrix

    rng = np.random.default_rng(31)
    seen = 0
    for _ in range(10):
        frames = generated_tracks(rng, int(rng.integers(20, 80)))
        acc, tally = mm.MOTAccumulator(auto_id=True), MotTally()
        for truth_ids, truth_xy, hyp_ids, hyp_xy in frames:
            acc.update(np.asarray(truth_ids).tolist(), np.asarray(hyp_ids).tolist(),
                       _distance_matrix(truth_xy, hyp_xy, 2.0))
            tally.add_frame(truth_ids, truth_xy, hyp_ids, hyp_xy)
        events = acc.mot_events
        want = events[events["Type"] == "SWITCH"]["OId"].astype(int).value_counts().to_dict()
        assert dict(tally.switches_of) == want
        assert sum(tally.switches_of.values()) == tally.result()["id_switches"]
        seen += len(want)
    assert seen > 5


def test_a_demo_record_gets_the_evals_baseline_and_every_rsus_clock_from_the_obu_metrics():
    """The live driver feeds no own frames: build_report computes the baseline from scenario, seed, start
    and cycle times, the eval's figures for the same run; the OBU's metrics give each RSU's clock."""
    from schemas.messages import ObuMetrics, RsuLinkStatus
    from v2i.offline.runner import OfflineRun
    from v2i.offline.spec import EVAL_EPOCH_NS, RunRecord, RunSpec, build_report
    from v2i.sim.obu_sources import SimulatedVehicle
    from v2i.sim.world import World

    spec = RunSpec(scenario="red-light-runner", seed=4, duration_s=12.0, rsu_clock_offset_ms=30.0)
    run = OfflineRun(spec)
    run.execute()
    world = World(run.scenario, ego=run.scenario.vehicles[0].name)
    cycles = SimulatedVehicle(world, spec.seed, EVAL_EPOCH_NS).cycle_times_ns(12.0)
    record = RunRecord(world, EVAL_EPOCH_NS, 12.0, cycles)
    t_ns = EVAL_EPOCH_NS + 6 * 10**9
    true_ns = 30_000_000
    # (mode, rsu-a's error, the RSUs the cycle used: None from a producer that does not say, rsu-a's steps)
    for mode, off_ms, inputs, steps in (("intra", 2.0, None, 0), ("vehicle-only", 9.0, None, 0),
                                        ("inter", 20.0, ("rsu-b",), 1)):
        rsus = (RsuLinkStatus(rsu_id="rsu-a", clock_offset_ns=true_ns + round(off_ms * 1e6), clock_offset_naive_ns=true_ns,
                              clock_drift_ppm=0.0, clock_steps=steps),
                RsuLinkStatus(rsu_id="rsu-b", clock_offset_ns=true_ns - 1_000_000, clock_offset_naive_ns=true_ns,
                              clock_drift_ppm=0.0))
        record.add_obu_metrics(ObuMetrics(vehicle_id="ego", t_ns=t_ns, mode=mode, rsus=rsus, rsu_inputs=inputs))
        t_ns += 100_000_000
    report = build_report(spec, world, record, "demo")
    assert report["vehicle_only"] == run.report()["vehicle_only"]
    assert set(report["clock_rsus"]) == {"rsu-a", "rsu-b"}
    # the intra cycle's 2 ms (every synced RSU: no rsu_inputs), not the vehicle-only 9 ms nor rsu-a's 20 ms
    # in a cycle that used rsu-b only
    assert report["clock_error_when_fused_max_ms"] == pytest.approx(2.0)
    assert report["clock_offset_error_ms"]["max"] == pytest.approx(20.0)
    assert report["clock_steps_detected"] == 1 and report["clock_rsus"]["rsu-a"]["steps_detected"] == 1
