"""Which RSUs a cycle's output used (``ObuPipeline.last_rsu_inputs``) and mode gating by clock uncertainty."""

import msgpack
import pytest
from pydantic import ValidationError

from v2i.core.frames import Pose2D
from v2i.fusion.wire import states_from_objects
from obu_service.config import ObuConfig
from obu_service.fusion_mode import MODE_REASONS, Feasible, mode_reason
from obu_service.pipeline import ObuPipeline, ObuPipelineConfig
from rsu_service.pipeline import answer_time_request
from schemas.codec import decode, encode
from schemas.messages import FusedObjectList, ObjectList, ObjectListHeader
from v2i.services import obu_scenario_site
from test_obu_pipeline import MS, THETA, T0, five_hz, objs, predictions, rsu_list, synced_pipeline


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


def sync(p: ObuPipeline, rsu_id: str, round_trip_ns: int, t1_ns: int = T0) -> None:
    """One time exchange with ``rsu_id`` whose round trip is ``round_trip_ns`` (symmetric): its
    offset is THETA and its stated uncertainty about half the round trip."""
    req = p.make_time_request(t1_ns)
    at_rsu = t1_ns + round_trip_ns // 2 + THETA
    p.on_time_reply(answer_time_request(req, rsu_id, at_rsu, at_rsu), t1_ns + round_trip_ns)


def rsu_frame(rsu_id: str, capture_obu_ns: int, xy, seq: int = 0) -> ObjectList:
    header = ObjectListHeader(rsu_id=rsu_id, seq=seq, capture_time_ns=capture_obu_ns + THETA,
                              publish_time_ns=capture_obu_ns + THETA + 50 * MS)
    return ObjectList(header=header, objects=states_from_objects(objs([xy])))


def test_an_rsu_with_an_uncertain_clock_is_not_fused_and_a_good_one_still_is():
    p = ObuPipeline(ObuPipelineConfig(fusion="iou-merge", fusion_mode="inter"))
    sync(p, "good", 10 * MS, T0 + 2_500 * MS)  # uncertainty ~5 ms: within the tracking bound (50 ms)
    sync(p, "vague", 2_000 * MS, T0 + 20 * MS)  # ~1 s: far past it
    cycle = T0 + 3_000 * MS
    p.on_pose(cycle, Pose2D(0.0, 0.0, 0.0))
    p.on_rsu_message(rsu_frame("vague", cycle - 100 * MS, [20.0, 5.0]), cycle - 30 * MS)
    p.on_detections(objs([[8.0, 0.0]]), cycle)  # (the replies, held briefly, are in the clock filters by now)
    assert p.clock_offset("vague", cycle).uncertainty_ns > 50 * MS >= p.clock_offset("good", cycle).uncertainty_ns
    out = p.fuse(cycle + 20 * MS)
    assert (out.mode, out.mode_reason, p.last_rsu_inputs) == ("vehicle-only", "clock_uncertainty", ())
    assert len(out.objects) == 1  # only the own object: the vague RSU's was withheld
    cycle += 100 * MS
    p.on_rsu_message(rsu_frame("vague", cycle - 100 * MS, [21.0, 5.0], seq=1), cycle - 30 * MS)
    p.on_rsu_message(rsu_frame("good", cycle - 100 * MS, [-30.0, 5.0]), cycle - 30 * MS)
    p.on_detections(objs([[8.0, 0.0]]), cycle)
    out = p.fuse(cycle + 20 * MS)
    assert (out.mode, out.mode_reason, p.last_rsu_inputs) == ("inter", "best", ("good",))
    assert len(out.objects) == 2  # own + the good RSU's (the vague one's at x = 21 m is not there)
    assert min(abs(o.x - 21.0) for o in out.objects) > 5.0
    assert p.mode_reasons == {"clock_uncertainty": 1, "best": 1}
    metrics = p.metrics(cycle)
    assert metrics.mode_reasons == {"clock_uncertainty": 1, "best": 1} and metrics.rsu_inputs == ("good",)
    assert {r.rsu_id: r.clock_steps for r in metrics.rsus} == {"good": 0, "vague": 0}


def test_planning_has_its_own_looser_bound():
    for round_trip_ms, mode, inputs in ((400, "planning", ("rsu1",)), (2_000, "vehicle-only", ())):
        p = ObuPipeline(ObuPipelineConfig(fusion="kf"))
        sync(p, "rsu1", round_trip_ms * MS, T0 + 800 * MS)  # uncertainty ~200 ms (within planning's 500 ms) or ~1 s
        cycle = T0 + 3_000 * MS
        p.on_pose(cycle, Pose2D(0.0, 0.0, 0.0))
        p.on_rsu_message(rsu_list(cycle - 100 * MS, [-40.0, 0.0], [10.0, 0.0]), cycle - 30 * MS)
        p.on_predictions(predictions(cycle - 100 * MS, [-40.0, 0.0], [10.0, 0.0]), cycle - 30 * MS)
        p.on_detections(objs([[8.0, 5.0]]), cycle)
        out = p.fuse(cycle + 20 * MS)
        # the frame (good for inter) is withheld in both; the paths only past planning's bound
        assert (out.mode, out.mode_reason, p.last_rsu_inputs) == (mode, "clock_uncertainty", inputs)
        assert (p.last_planning is not None) == (mode == "planning")


def test_mode_reason_says_why_the_mode_is_not_the_best():
    nothing, inter = Feasible(), Feasible(inter=True)
    assert mode_reason("adaptive", "inter", inter, set()) == "best"
    assert mode_reason("adaptive", "intra", Feasible(intra=True, inter=True), set()) == "best"
    assert mode_reason("planning", "planning", Feasible(planning=True), {"tracking"}) == "best"  # fixed: as configured
    assert mode_reason("adaptive", "vehicle-only", inter, set()) == "hysteresis"  # climbing back up
    assert mode_reason("adaptive", "planning", Feasible(planning=True), {"tracking"}) == "clock_uncertainty"
    assert mode_reason("adaptive", "vehicle-only", nothing, {"planning"}) == "clock_uncertainty"
    assert mode_reason("adaptive", "planning", Feasible(planning=True), {"planning"}) == "no_rsu_data"  # not above
    assert mode_reason("intra", "vehicle-only", nothing, set(), intra_late=True) == "intra_frame_late"
    assert mode_reason("adaptive", "vehicle-only", nothing, set(), not_synced=True) == "not_synced"
    assert mode_reason("inter", "vehicle-only", nothing, set()) == "no_rsu_data"
    assert set(MODE_REASONS) >= {"best", "hysteresis", "clock_uncertainty", "not_synced", "no_rsu_data"}


def test_an_unsynchronised_rsu_and_a_late_intra_frame_are_named():
    p = ObuPipeline(ObuPipelineConfig(fusion="kf"))
    cycle = T0 + 1_000 * MS
    p.on_rsu_message(rsu_list(cycle - 100 * MS, [10.0, 0.0], [0, 0]), cycle - 30 * MS)
    p.on_detections(objs([[8.0, 0.0]]), cycle)
    assert p.fuse(cycle).mode_reason == "not_synced"
    q = synced_pipeline(fusion_mode="intra")
    last = five_hz(q, T0 + 1_000_000_000, 5)
    fuse_by = q.on_detections(objs([[8.0, 0.0]]), last + 210 * MS)  # its slot's frame never comes
    out = q.fuse(fuse_by)
    assert (out.mode, out.mode_reason) == ("vehicle-only", "intra_frame_late")


def test_an_old_producer_without_mode_reason_still_decodes():
    msg = FusedObjectList(vehicle_id="car-1", seq=1, cycle_time_ns=T0, publish_time_ns=T0, mode="inter", ego_x=1.0)
    assert decode(encode(msg), FusedObjectList).mode_reason == ""  # the field is nil: not on the wire
    new = msg.model_copy(update={"mode_reason": "clock_uncertainty"})
    assert decode(encode(new), FusedObjectList) == new
    envelope = msgpack.unpackb(encode(new))
    assert envelope[2][-1] == "clock_uncertainty"  # the last positional field: older lists are a prefix of it


def test_the_obu_config_exposes_the_bounds_and_keeps_planning_the_looser():
    config = ObuConfig(max_clock_uncertainty_ms=20.0, planning_max_clock_uncertainty_ms=300.0)
    _, site = obu_scenario_site(config)
    pipeline = config.pipeline_config(site)
    assert (pipeline.max_clock_uncertainty_ms, pipeline.planning_max_clock_uncertainty_ms) == (20.0, 300.0)
    with pytest.raises(ValidationError, match="planning's bound is the looser one"):
        ObuConfig(max_clock_uncertainty_ms=600.0)
    with pytest.raises(ValueError):
        ObuPipelineConfig(max_clock_uncertainty_ms=600.0, planning_max_clock_uncertainty_ms=500.0)
