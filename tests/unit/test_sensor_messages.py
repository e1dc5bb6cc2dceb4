"""Sensor input messages (schemas.sensor_messages): exact round trips, every refusal reason, keys."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas import keys
from schemas.codec import (CodecError, InvalidMessage, MalformedMessage, SchemaVersionError, WrongMessageType, decode,
                           encode)
from schemas.messages import MAX_OBJECTS, SCHEMA_VERSION, ObjectList, ObjectState
from schemas.sensor_messages import (GroundTruth, LocalizationPose, SensorHeader, SensorObjects, VehicleTruth)
from schemas.wire_view import pack_view, unpack_view

T0 = 1_700_000_000_000_000_000
MS = 1_000_000


def car(i: int = 0, **changes) -> ObjectState:
    return ObjectState(**{"id": i, "cls": 1, "x": 10.0 + i, "y": -3.25, "length": 4.5, "width": 1.8, **changes})


def header(**changes) -> SensorHeader:
    return SensorHeader(**{"sensor_id": "rsu1", "sensor": "camera", "seq": 7, "frame_id": "map",
                           "capture_time_ns": T0, "ready_time_ns": T0 + 90 * MS, **changes})


def sensor_objects(n: int = 3, **changes) -> SensorObjects:
    return SensorObjects(header=header(**changes), objects=tuple(car(i) for i in range(n)))


def pose(**changes) -> LocalizationPose:
    return LocalizationPose(**{"vehicle_id": "ego", "seq": 3, "t_ns": T0, "x": 1.5, "y": -2.0, "yaw": 0.3, "vx": 8.0,
                               "cov_xx": 0.0025, "cov_yy": 0.0025, "cov_yawyaw": 2.5e-5, "correlation_time_s": 5.0,
                               **changes})


def truth() -> GroundTruth:
    return GroundTruth(seq=1, t_ns=T0, scenario="red-light-runner", objects=(car(1), car(2)),
                       vehicles=(VehicleTruth(vehicle_id="ego", x=0.0, y=1.0, yaw=0.1, vx=10.0, length=4.6,
                                              width=1.9, height=1.5),))


def body_of(data: bytes) -> dict:
    return unpack_view(data)


def pack(envelope: dict) -> bytes:
    return pack_view(envelope)


@pytest.mark.parametrize("msg", [sensor_objects(), sensor_objects(0, frame_id="base_link", sensor_id="ego"),
                                 pose(), truth()])
def test_round_trip_is_exact(msg) -> None:
    assert decode(encode(msg), type(msg)) == msg


def test_objects_travel_as_columns() -> None:
    objects = body_of(encode(sensor_objects(5)))["d"]["objects"]
    assert objects["n"] == 5 and isinstance(objects["rows"], bytes) and 0 < len(objects["rows"]) < 5 * 20


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=512))
def test_random_bytes_raise_only_codec_errors(data: bytes) -> None:
    for model in (SensorObjects, LocalizationPose, GroundTruth):
        with pytest.raises(CodecError):
            decode(data, model)


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_bit_flips_raise_only_codec_errors_or_decode(data) -> None:
    raw = bytearray(encode(sensor_objects(4)))
    for i in data.draw(st.lists(st.integers(0, len(raw) - 1), min_size=1, max_size=6)):
        raw[i] ^= 1 << data.draw(st.integers(0, 7))
    try:
        decode(bytes(raw), SensorObjects)
    except CodecError:
        pass


@pytest.mark.parametrize("where", ["header", "body"])
def test_unknown_fields_are_malformed(where: str) -> None:
    # fields travel by position (schemas.codec): an unknown one is an entry too many
    env = body_of(encode(sensor_objects()))
    (env["d"]["header"] if where == "header" else env["d"])["evil"] = 1
    with pytest.raises(MalformedMessage, match="at most"):
        decode(pack(env), SensorObjects)


def test_versions_are_checked_in_envelope_and_header() -> None:
    env = body_of(encode(sensor_objects()))
    env["v"] = SCHEMA_VERSION + 1
    with pytest.raises(SchemaVersionError):
        decode(pack(env), SensorObjects)
    env = body_of(encode(sensor_objects()))
    env["d"]["header"]["schema_version"] = SCHEMA_VERSION - 1
    with pytest.raises(SchemaVersionError, match="states schema version"):
        decode(pack(env), SensorObjects)
    env = body_of(encode(pose()))
    env["d"]["schema_version"] = 0
    with pytest.raises(SchemaVersionError):
        decode(pack(env), LocalizationPose)


def test_other_message_types_are_refused_by_tag() -> None:
    with pytest.raises(WrongMessageType):
        decode(encode(pose()), SensorObjects)
    ol = ObjectList(header={"rsu_id": "rsu1", "seq": 0, "capture_time_ns": T0, "publish_time_ns": T0})
    with pytest.raises(WrongMessageType):
        decode(encode(ol), SensorObjects)


@pytest.mark.parametrize("field", ["capture_time_ns", "ready_time_ns"])
@pytest.mark.parametrize("bad", [0, -1, 2**63 - 1])
def test_absurd_header_times_are_invalid(field: str, bad: int) -> None:
    env = body_of(encode(sensor_objects()))
    env["d"]["header"][field] = bad
    with pytest.raises(InvalidMessage, match=f"header.{field}"):
        decode(pack(env), SensorObjects)


@pytest.mark.parametrize("ready_ms, reason", [(-1, "before capture_time_ns"), (10_001, "at most 10 s")])
def test_ready_time_must_follow_capture_within_ten_seconds(ready_ms: int, reason: str) -> None:
    env = body_of(encode(sensor_objects()))
    env["d"]["header"]["ready_time_ns"] = T0 + ready_ms * MS
    with pytest.raises(InvalidMessage, match=reason):
        decode(pack(env), SensorObjects)


@pytest.mark.parametrize("frame", ["odom", "", "MAP"])
def test_frame_must_be_map_or_base_link(frame: str) -> None:
    env = body_of(encode(sensor_objects()))
    env["d"]["header"]["frame_id"] = frame
    with pytest.raises(InvalidMessage, match="frame_id"):
        decode(pack(env), SensorObjects)


@pytest.mark.parametrize("sensor_id", ["", "a/b", "*", "x" * 65])
def test_sensor_id_must_be_an_id(sensor_id: str) -> None:
    env = body_of(encode(sensor_objects()))
    env["d"]["header"]["sensor_id"] = sensor_id
    with pytest.raises(InvalidMessage, match="sensor_id"):
        decode(pack(env), SensorObjects)


def test_too_many_objects_are_invalid_before_decoding_them() -> None:
    env = body_of(encode(sensor_objects(1)))
    env["d"]["objects"]["n"] = MAX_OBJECTS + 1
    with pytest.raises(InvalidMessage, match=f"at most {MAX_OBJECTS}"):
        decode(pack(env), SensorObjects)


def test_truncated_column_is_malformed() -> None:
    env = body_of(encode(sensor_objects(3)))
    env["d"]["objects"]["rows"] = env["d"]["objects"]["rows"][:-1]
    with pytest.raises(MalformedMessage, match="rows are"):
        decode(pack(env), SensorObjects)


@pytest.mark.parametrize("field", ["x", "y", "yaw", "vx", "cov_xx", "cov_yawyaw", "correlation_time_s"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_pose_values_are_invalid(field: str, bad: float) -> None:
    env = body_of(encode(pose()))
    env["d"][field] = bad
    with pytest.raises(InvalidMessage, match=field):
        decode(pack(env), LocalizationPose)


@pytest.mark.parametrize("field, bad", [("x", 1e7), ("vx", 201.0), ("cov_xx", -1.0), ("cov_yawyaw", 11.0),
                                        ("correlation_time_s", -1.0)])
def test_out_of_range_pose_values_are_invalid(field: str, bad: float) -> None:
    env = body_of(encode(pose()))
    env["d"][field] = bad
    with pytest.raises(InvalidMessage, match=field):
        decode(pack(env), LocalizationPose)


def test_pose_covariance_must_be_positive_semi_definite() -> None:
    with pytest.raises(ValueError, match="positive semi-definite"):
        pose(cov_xx=1.0, cov_yy=1.0, cov_xy=2.0)
    env = body_of(encode(pose()))
    env["d"]["cov_xyaw"] = 0.5  # |cov_xyaw| > sqrt(cov_xx cov_yawyaw)
    with pytest.raises(InvalidMessage, match="positive semi-definite"):
        decode(pack(env), LocalizationPose)


def test_pose_covariance_matrix() -> None:
    cov = pose(cov_xy=0.001, cov_xyaw=1e-5).covariance()
    assert cov.shape == (3, 3) and np.allclose(cov, cov.T) and cov[0, 2] == pytest.approx(1e-5)


def test_ground_truth_frame_is_map_only() -> None:
    env = body_of(encode(truth()))
    env["d"]["frame_id"] = "base_link"
    with pytest.raises(InvalidMessage, match="frame_id"):
        decode(pack(env), GroundTruth)


def test_sensor_keys() -> None:
    assert keys.sensor_rsu_objects("rsu1") == "v2x/sensor/rsu/rsu1/objects"
    assert keys.sensor_vehicle_objects("ego") == "v2x/sensor/vehicle/ego/objects"
    assert keys.sensor_vehicle_pose("ego") == "v2x/sensor/vehicle/ego/pose"
    assert keys.WORLD_TRUTH == "v2x/world/truth"
    for builder in (keys.sensor_rsu_objects, keys.sensor_vehicle_objects, keys.sensor_vehicle_pose):
        with pytest.raises(ValueError, match="invalid id"):
            builder("a/*")


def test_sensor_keys_never_meet_what_the_link_relays_or_the_obu_publishes() -> None:
    """An input key must not intersect any key expression the emulator relays or a node publishes:
    otherwise a relayed RSU list could arrive as a sensor input, or the reverse."""
    inputs = [keys.sensor_rsu_objects("rsu1"), keys.sensor_vehicle_objects("ego"), keys.sensor_vehicle_pose("ego"),
              keys.WORLD_TRUTH, "v2x/sensor/**"]
    relayed = ["v2x/rsu/**", "v2x/obu/**", "v2x/link/**", keys.RSU_OBJECTS_ALL, keys.RSU_PREDICTIONS_ALL,
               keys.RSU_TIME_ALL, keys.RSU_IMAGE_FEATURES_ALL]
    for a in inputs:
        for b in relayed:
            assert not zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b)), (a, b)
    assert keys.rsu_id_or_none(keys.sensor_rsu_objects("rsu1")) is None


# --- the nodes' screening of sensor inputs (v2i.runtime.sensor_screen) --------------------------------


def screen(**limits):
    from v2i.runtime.sensor_screen import SensorLimits, SensorScreen

    return SensorScreen("rsu1", "map", SensorLimits(**limits))


def refused(fn, *args) -> str:
    from v2i.runtime.sensor_screen import InputRefused

    with pytest.raises(InputRefused) as info:
        fn(*args)
    return info.value.reason


def test_screen_accepts_a_valid_frame_and_then_only_newer_ones() -> None:
    s = screen()
    receive = T0 + 100 * MS
    assert s.objects(encode(sensor_objects(2)), receive).header.seq == 7
    assert refused(s.objects, encode(sensor_objects(2)), receive) == "input_out_of_order"  # a replay
    later = sensor_objects(2, capture_time_ns=T0 + 200 * MS, ready_time_ns=T0 + 290 * MS)
    assert len(s.objects(encode(later), T0 + 300 * MS).objects) == 2


@pytest.mark.parametrize("payload, reason", [
    (b"\x00garbage", "input_malformed"),
    (encode(pose()), "input_wrong_type"),
    (encode(sensor_objects(sensor_id="rsu2")), "input_wrong_sensor"),
    (encode(sensor_objects(frame_id="base_link")), "input_wrong_frame"),
    (encode(sensor_objects(capture_time_ns=T0 + 500 * MS, ready_time_ns=T0 + 500 * MS)), "input_future"),
    (encode(sensor_objects(capture_time_ns=T0 - 2000 * MS, ready_time_ns=T0 - 1900 * MS)), "input_stale"),
    (encode(sensor_objects(9)), "input_too_many_objects"),
])
def test_screen_refusals_are_counted_by_reason(payload: bytes, reason: str) -> None:
    assert refused(screen(max_objects=8).objects, payload, T0 + 100 * MS) == reason


def test_screen_refuses_large_payloads_before_reading_them() -> None:
    payload = encode(sensor_objects(100))
    assert refused(screen(max_bytes=len(payload) - 1).objects, payload, T0 + 100 * MS) == "input_too_large"


def test_screen_checks_poses_by_vehicle() -> None:
    from v2i.runtime.sensor_screen import SensorScreen

    s = SensorScreen("ego", "base_link")
    assert s.pose(encode(pose()), T0 + 5 * MS).x == 1.5
    assert refused(s.pose, encode(pose()), T0 + 10 * MS) == "input_out_of_order"
    assert refused(s.pose, encode(pose(vehicle_id="car2", t_ns=T0 + 50 * MS)), T0 + 60 * MS) == "input_wrong_sensor"
    assert refused(s.pose, encode(pose(t_ns=T0 + 900 * MS)), T0 + 100 * MS) == "input_future"


def test_received_pose_keeps_its_error_statistics() -> None:
    from obu_service.source import pose_of

    p = pose_of(pose(cov_xyaw=1e-6))
    assert (p.x, p.y, p.yaw) == (1.5, -2.0, pytest.approx(0.3, abs=1e-3))
    assert p.uncertainty.cov[0, 2] == 1e-6 and p.uncertainty.correlation_time_s == 5.0
    assert pose_of(pose(cov_xx=0.0, cov_yy=0.0, cov_yawyaw=0.0)).uncertainty is None


# --- the OBU's cycle clock with outside detections (obu_service.source.ExternalCycles) --------------


def test_external_cycles_follow_frames_and_fill_gaps_on_time() -> None:
    from obu_service.source import ExternalCycles

    cycles = ExternalCycles(start_ns=T0, period_ns=100 * MS, wait_ns=90 * MS)
    assert cycles.gap_due_ns == T0 + 90 * MS and cycles.gap(T0 + 89 * MS) is None
    assert cycles.accept(T0 + 3 * MS)  # a frame of the first slot (any phase)
    assert cycles.gap_due_ns == T0 + 193 * MS
    assert cycles.gap(T0 + 193 * MS) == T0 + 103 * MS  # the frame of that slot never came
    assert not cycles.accept(T0 + 104 * MS)  # ... and comes too late: its slot went out
    assert cycles.accept(T0 + 205 * MS)  # the next one starts its own cycle
    assert cycles.gap(T0 + 394 * MS) is None and cycles.gap(T0 + 395 * MS) == T0 + 305 * MS
