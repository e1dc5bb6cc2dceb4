"""The offline runner: deterministic per seed, and V2I sees the runner far earlier. The run
record scores each output as it arrives: its memory per output is a few hundred bytes, and
the live demo feeds it through a bounded queue with the same numbers as a direct feed."""

import gc
import json
import threading
import tracemalloc
from types import SimpleNamespace

import numpy as np
import pytest

from v2i.orchestration.demo import Demo
from v2i.orchestration.inbox_scoring import INBOX_MESSAGES
from v2i.offline.runner import OfflineRun
from v2i.offline.spec import EVAL_EPOCH_NS, RunRecord, RunSpec, build_report
from v2i.core.frames import map_to_base
from v2i.fusion.wire import states_from_objects
from schemas.codec import decode, encode
from schemas.messages import SOURCE_VEHICLE, FusedObjectList, ObuMetrics, RsuLinkStatus
from v2i.sim.scenario import load_scenario
from v2i.sim.world import World
from v2i.cli import main

REQUIRED = {"scenario", "profile", "fusion", "seed", "duration_s", "cycles", "output_deadline_miss_ratio",
            "target", "vehicle_only", "clock_offset_error_ms"}


def report(seed: int, **kw) -> dict:
    run = OfflineRun(RunSpec(seed=seed, duration_s=12.0, **kw))
    return build_report(run.spec, run.world, run.execute(), driver="eval")


def test_same_seed_same_report_other_seed_differs():
    a, b, c = report(1), report(1), report(2)
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    assert a["target"] != c["target"]
    assert REQUIRED <= set(a)
    assert {"mean_bev_iou", "rmse_m", "first_detection_distance_m"} <= set(a["target"])
    assert {"p50", "p95", "max"} <= set(a["clock_offset_error_ms"])


def test_v2i_first_detection_at_least_three_times_vehicle_only():
    r = report(0)
    assert r["target"]["first_detection_distance_m"] >= 3 * r["vehicle_only"]["first_detection_distance_m"]
    assert r["output_deadline_miss_ratio"] == 0.0


def test_clock_offset_is_recovered_offline():
    r = report(0, rsu_clock_offset_ms=350.0, rsu_clock_drift_ppm=20.0)
    assert r["clock_offset_error_ms"]["p95"] < 10.0


def test_vehicle_only_fusion_never_uses_rsu():
    r = report(0, fusion="vehicle-only")
    assert r["mode_share"]["vehicle_only"] == 1.0


def test_own_only_kf_is_the_vehicle_only_baseline():
    """--fusion kf-vehicle runs the baseline's tracker (v2i.offline.baseline) on the same own frames."""
    r = report(0, fusion="kf-vehicle")
    assert r["target"] == r["vehicle_only"] and r["target"]["detected_cycles"] > 0


def test_cli_rejects_unknown_scenario_and_profile(capsys):
    assert main(["eval", "--scenario", "no-such-place"]) == 2
    assert "red-light-runner" in capsys.readouterr().err
    assert main(["eval", "--profile", "carrier-pigeon"]) == 2
    assert "lte-v2x" in capsys.readouterr().err


def test_cli_eval_json_stdout(capsys):
    assert main(["eval", "--duration", "3", "--json", "-"]) == 0
    out = capsys.readouterr()
    assert REQUIRED <= set(json.loads(out.out))
    assert "red-light-runner" in out.err


@pytest.mark.parametrize("cmd", ["demo", "eval", "rsu", "obu", "link"])
def test_every_subcommand_explains_itself(cmd, capsys):
    with pytest.raises(SystemExit) as exc:
        main([cmd, "--help"])
    assert exc.value.code == 0
    assert len(capsys.readouterr().out) > 200


def true_output(world: World, k: int, mode: str = "intra") -> FusedObjectList:
    """Cycle k (10 Hz from EVAL_EPOCH_NS): every actor within 80 m, where it truly is (base_link)."""
    t_s = 0.1 * k
    truth = map_to_base(world.actors_at(t_s), world.ego_at(t_s))
    near = truth.take(np.linalg.norm(truth.xy, axis=1) <= 80.0)
    n = len(near)
    near = near.with_(sources=np.full(n, SOURCE_VEHICLE), confidence=np.full(n, 0.9),
                      cov_xy=np.tile(np.eye(2), (n, 1, 1)))
    t_ns = EVAL_EPOCH_NS + k * 100_000_000
    return FusedObjectList(vehicle_id="car", seq=k, cycle_time_ns=t_ns, publish_time_ns=t_ns + 20_000_000, mode=mode,
                           objects=states_from_objects(near, fused=True))


def test_record_memory_per_output_is_a_few_hundred_bytes():
    # Kept per output: 17 B cycle log, 10 B per object in range (AP), 2 x 56 B while the target
    # is detected (fused and vehicle-only). Keeping the messages, as the demo did, costs their
    # size (0.8 kB encoded here, several kB decoded) per output.
    world = World(load_scenario("red-light-runner"))
    warm = RunRecord(world, EVAL_EPOCH_NS, 40.0)
    for k in range(0, 200, 5):  # every code path once (lazy imports) before memory is traced
        warm.add_output(true_output(world, k))
    warm.target.score()  # (its pending IoU and NEES too)
    tracemalloc.start()
    record = RunRecord(world, EVAL_EPOCH_NS, 40.0)
    for k in range(50):
        record.add_output(true_output(world, k))
    gc.collect()  # temporaries in reference cycles are not the record's
    before = tracemalloc.get_traced_memory()[0]
    for k in range(50, 350):  # 5-35 s: the target in range from 6 to 15 s, then the world stands still
        record.add_output(true_output(world, k))
    for tally in (record.target, record.vehicle_target):  # its pending cycles (at most PENDING x 144 B) scored
        tally.score()
    gc.collect()
    per_output_bytes = (tracemalloc.get_traced_memory()[0] - before) / 300
    tracemalloc.stop()
    assert record.target.score().detected_cycles > 50
    objects_in_range = max(len(true_output(world, k).objects) for k in (100, 349))
    assert per_output_bytes < 17 + 10 * objects_in_range + 2 * 56 + 30, per_output_bytes  # 30: arrays' spare room


def test_demo_scores_messages_from_its_queue_as_a_direct_feed_would():
    spec = RunSpec(duration_s=10.0)
    demo = Demo(spec)
    demo._tmp.cleanup()  # the demo's temporary folder (the link config): not needed without processes
    cycles = EVAL_EPOCH_NS + 100_000_000 * np.arange(100)
    demo.record, direct = (RunRecord(demo.world, EVAL_EPOCH_NS, 10.0, cycles) for _ in range(2))
    scorer = threading.Thread(target=demo._score_inbox)
    scorer.start()
    for k in range(60, 100):  # 6-10 s: the red-light runner comes into range
        out = encode(true_output(demo.world, k, mode="intra" if k < 80 else "vehicle-only"))
        status = RsuLinkStatus(rsu_id="rsu1", clock_offset_ns=1000 * k, clock_offset_naive_ns=2000 * k,
                               clock_drift_ppm=1.0, messages_accepted=k)
        metrics = encode(ObuMetrics(vehicle_id="car", t_ns=int(cycles[k]), covered_cycles=k, rsus=(status,)))
        for kind, data in (("objects", out), ("metrics", metrics)):
            demo._keep(kind, SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda d=data: d)))
        direct.add_output(decode(out, FusedObjectList))
        direct.add_obu_metrics(decode(metrics, ObuMetrics))
    demo._inbox.put(None)
    scorer.join(timeout=30.0)
    via_queue, fed = (build_report(spec, demo.world, r, driver="demo") for r in (demo.record, direct))
    assert via_queue == fed
    assert via_queue["outputs"] == 40 and via_queue["mode_share"]["vehicle_only"] == 0.5
    assert via_queue["output_deadline_miss_ratio"] == 0.6  # cycles 0-59 never published
    assert via_queue["rsu_messages_received"] == 99 and via_queue["clock_offset_error_ms"]["samples"] == 40
    assert via_queue["target"]["detected_cycles"] == 40 and not demo.dropped


def test_demo_callback_drops_and_counts_when_the_queue_is_full():
    demo = Demo(RunSpec(duration_s=1.0))
    demo._tmp.cleanup()
    sample = SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: b"x"))
    for _ in range(INBOX_MESSAGES + 5):
        demo._keep("objects", sample)  # no scorer: never blocks
    assert demo._inbox.qsize() == INBOX_MESSAGES and demo.dropped == {"objects": 5}


@pytest.mark.parametrize("step_ms", [-2000, -700, 500, 2000])
def test_rsu_clock_steps_of_either_sign_keep_the_run_going_and_the_obu_recovers(step_ms):
    """The issue's case (an RSU clock stepping back 700 ms killed the RSU): the run completes,
    every cycle is on time and the OBU's clock estimate is back under 1 ms within 3 s."""
    spec = RunSpec(seed=1, duration_s=24.0, rsu_clock_offset_ms=350, rsu_clock_drift_ppm=-85,
                   rsu_clock_step_ms=step_ms, rsu_clock_step_at_s=15.0)
    run = OfflineRun(spec)
    out = build_report(spec, run.world, run.execute(), driver="eval")
    assert out["output_deadline_miss_ratio"] == 0.0
    assert out["clock_step_recovery_s"] is not None and out["clock_step_recovery_s"] <= 3.0
    assert out["mode_share"]["vehicle_only"] < 0.1  # fusion resumed after the step


def test_the_lidar_frames_truth_is_the_cycles_truth_and_a_stale_one_is_not_taken():
    """RunRecord.add_output(..., truth=lidar.last_truth): the truth the LiDAR derived at the
    cycle's capture equals, array for array, the one CycleFrame.of derives itself; the scores of a
    record fed it equal those of one that is not; a truth of another time is not used."""
    from v2i.scoring.metrics import CycleFrame
    from v2i.sim.obu_sources import SimulatedVehicle

    world = World(load_scenario("red-light-runner"))
    sensing = SimulatedVehicle(world, 0, EVAL_EPOCH_NS)
    fed, plain = RunRecord(world, EVAL_EPOCH_NS, 40.0), RunRecord(world, EVAL_EPOCH_NS, 40.0)
    for k in range(60, 160):
        out = true_output(world, k)
        sensing.capture(out.cycle_time_ns)
        got = CycleFrame.of(world, out, EVAL_EPOCH_NS, sensing.lidar.last_truth).truth
        want = CycleFrame.of(world, out, EVAL_EPOCH_NS).truth
        assert got is sensing.lidar.last_truth[1]
        for name in ("ids", "xy", "yaw", "vxy", "lwh"):
            assert getattr(got, name).tobytes() == getattr(want, name).tobytes()
        fed.add_output(out, truth=sensing.lidar.last_truth)
        plain.add_output(out)
    assert fed.target.score() == plain.target.score() and fed.detection.scores() == plain.detection.scores()
    stale = (sensing.lidar.last_truth[0] - 0.1, sensing.lidar.last_truth[1])
    assert CycleFrame.of(world, true_output(world, 159), EVAL_EPOCH_NS, stale).truth is not stale[1]


def test_the_two_target_tallies_score_a_shared_frame_as_their_own_frames():
    """RunRecord's tallies (all sources, vehicle only) share each CycleFrame and its pair numbers
    (CycleFrame.pair_values): scores and series equal those of tallies each given a fresh frame,
    and a pair's numbers equal the ones computed from the arrays (IoU: bev_iou_matrix)."""
    from v2i.scoring.metrics import CycleFrame, TargetTally
    from v2i.fusion.geometry import bev_iou_matrix, bev_iou_pairs

    def box(objs, r):
        return np.r_[objs.xy[r], objs.lwh[r, :2], objs.yaw[r]][None]

    world = World(load_scenario("red-light-runner"))
    shared = TargetTally(world.target_id), TargetTally(world.target_id, sources_mask=SOURCE_VEHICLE)
    alone = TargetTally(world.target_id), TargetTally(world.target_id, sources_mask=SOURCE_VEHICLE)
    pairs = 0
    for k in range(60, 200):
        out = true_output(world, k)
        frame = CycleFrame.of(world, out, EVAL_EPOCH_NS)
        for tally in shared:
            tally.add(frame)
        for tally in alone:
            tally.add(CycleFrame.of(world, out, EVAL_EPOCH_NS))
        for (i, j), (sq_err, boxes, err, cov) in frame._pair_values.items():
            pair = np.array(boxes).reshape(2, 5)
            assert bev_iou_pairs(pair[:1], pair[1:])[0] == bev_iou_matrix(box(frame.truth, i), box(frame.out, j))[0, 0]
            assert sq_err == np.sum(np.square(frame.out.xy[j] - frame.truth.xy[i]))
            assert np.array(err).tobytes() == (frame.out.xy[j] - frame.truth.xy[i]).tobytes()
            assert np.array(cov).tobytes() == frame.out.cov_xy[j].tobytes()
            pairs += 1
    assert pairs > 50
    for a, b in zip(shared, alone):
        assert a.score() == b.score()
        sa, sb = a.series(), b.series()
        assert all(np.array_equal(getattr(sa, f), getattr(sb, f)) for f in ("t_s", "error_m", "out_xy", "sources"))
