"""Codec properties: exact round trip, only CodecError on hostile bytes, every model rule on decode."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas import (
    MAX_MESSAGE_BYTES,
    MAX_OBJECTS,
    SCHEMA_VERSION,
    CodecError,
    EgoPose,
    FusedObject,
    FusedObjectList,
    InvalidMessage,
    MalformedMessage,
    MessageTooLarge,
    ObjectClass,
    ObjectList,
    ObjectListHeader,
    PredictedPath,
    PredictionList,
    ObjectState,
    ObuMetrics,
    RsuLinkStatus,
    SchemaVersionError,
    TimeReply,
    TimeRequest,
    WrongMessageType,
    decode,
    encode,
)
from schemas.codec import LIST_TAGS
from schemas.columns import COLUMN, ObjectColumns
from schemas.messages import MAX_TIME_NS, MIN_TIME_NS, YAW_RATE_MAX
from schemas.wire_view import pack_view, unpack_view

FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
T0 = 1_700_000_000 * 10**9

# ---------------------------------------------------------------- strategies


def floats(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


times = st.integers(MIN_TIME_NS, MAX_TIME_NS)
node_ids = st.from_regex(r"[A-Za-z0-9_-]{1,64}", fullmatch=True)
seqs = st.integers(0, 2**63 - 1)
counts = st.integers(0, 2**63 - 1)
labels = st.text(max_size=32)

OBJECT_FIELDS = dict(
    id=st.integers(0, 2**32 - 1),
    cls=st.sampled_from(ObjectClass),
    x=floats(-1e6, 1e6),
    y=floats(-1e6, 1e6),
    z=floats(-1e4, 1e4),
    length=floats(0, 100),
    width=floats(0, 100),
    height=floats(0, 100),
    yaw=floats(-100, 100),
    vx=floats(-200, 200),
    vy=floats(-200, 200),
    ax=floats(-100, 100),
    ay=floats(-100, 100),
    yaw_rate=floats(-YAW_RATE_MAX, YAW_RATE_MAX),
    cov_xx=floats(0, 1e4),
    cov_xy=floats(-1e4, 1e4),
    cov_yy=floats(0, 1e4),
    confidence=floats(0, 1),
    age_s=floats(0, 1e6),
)
object_states = st.builds(ObjectState, **OBJECT_FIELDS)
fused_objects = st.builds(FusedObject, **OBJECT_FIELDS, sources=st.integers(0, 255))
ordered_times = st.tuples(times, times).map(sorted)


@st.composite
def object_lists(draw) -> ObjectList:
    capture, publish = draw(ordered_times)
    header = ObjectListHeader(
        rsu_id=draw(node_ids),
        seq=draw(seqs),
        capture_time_ns=capture,
        publish_time_ns=publish,
        frame_id=draw(st.text(max_size=64)),
        sensor=draw(st.text(max_size=128)),
    )
    return ObjectList(header=header, objects=tuple(draw(st.lists(object_states, max_size=12))))


@st.composite
def fused_object_lists(draw) -> FusedObjectList:
    cycle, publish = draw(ordered_times)
    return FusedObjectList(
        vehicle_id=draw(node_ids),
        seq=draw(seqs),
        cycle_time_ns=cycle,
        publish_time_ns=publish,
        fusion=draw(labels),
        mode=draw(labels),
        ego_x=draw(floats(-1e6, 1e6)),
        ego_y=draw(floats(-1e6, 1e6)),
        ego_yaw=draw(floats(-100, 100)),
        mode_reason=draw(labels),
        objects=tuple(draw(st.lists(fused_objects, max_size=12))),
    )


@st.composite
def time_replies(draw) -> TimeReply:
    t2, t3 = draw(ordered_times)
    return TimeReply(rsu_id=draw(node_ids), seq=draw(seqs), t1_ns=draw(times), t2_ns=t2, t3_ns=t3)


time_requests = st.builds(TimeRequest, obu_id=node_ids, seq=seqs, t1_ns=times)
ego_poses = st.builds(
    EgoPose,
    vehicle_id=node_ids,
    t_ns=times,
    x=floats(-1e6, 1e6),
    y=floats(-1e6, 1e6),
    yaw=floats(-100, 100),
    vx=floats(-200, 200),
    vy=floats(-200, 200),
)
int64s = st.integers(-(2**63), 2**63 - 1)
link_statuses = st.builds(
    RsuLinkStatus,
    rsu_id=node_ids,
    clock_offset_ns=st.none() | int64s,
    clock_uncertainty_ns=st.none() | int64s,
    sync_samples=counts,
    messages_accepted=counts,
    last_data_age_ms=st.none() | st.floats(allow_nan=False, allow_infinity=False),
)
obu_metrics = st.builds(
    ObuMetrics,
    vehicle_id=node_ids,
    t_ns=times,
    cycles=counts,
    output_deadline_misses=counts,
    mode=labels,
    rsus=st.lists(link_statuses, max_size=3).map(tuple),
    rejected=st.dictionaries(st.text(max_size=64), counts, max_size=4),
)


@st.composite
def prediction_lists(draw) -> PredictionList:
    base = draw(object_lists())
    steps = draw(st.integers(0, 6))
    paths = tuple(
        PredictedPath(id=o.id, x=draw(st.lists(floats(-1e6, 1e6), min_size=steps, max_size=steps)),
                      y=draw(st.lists(floats(-1e6, 1e6), min_size=steps, max_size=steps)),
                      yaw=draw(st.lists(floats(-100, 100), min_size=steps, max_size=steps)))
        for o in base.objects
    )
    return PredictionList(header=base.header, step_ns=draw(st.integers(1_000_000, 10_000_000_000)),
                          objects=base.objects, paths=paths)


messages = st.one_of(object_lists(), fused_object_lists(), time_requests, time_replies(), ego_poses, obu_metrics,
                     prediction_lists())
MODELS = [ObjectList, FusedObjectList, TimeRequest, TimeReply, EgoPose, ObuMetrics, PredictionList]

# ---------------------------------------------------------------- helpers


def envelope(tag: str, body: object, version: object = SCHEMA_VERSION) -> bytes:
    """An envelope of a named body (an object list's goes out as its array envelope)."""
    return pack_view({"v": version, "t": LIST_TAGS.get(tag, tag), "d": body})


def body_of(data: bytes) -> dict:
    return unpack_view(data)["d"]


def present_index(name: str, body: dict) -> int:
    """Position of a column among the present ones of an objects section (its width and ref)."""
    mask = body["objects"]["present"]
    j = COLUMN[name]
    assert mask >> j & 1, f"{name} not present"
    return bin(mask & ((1 << j) - 1)).count("1")


def header(**changes) -> ObjectListHeader:
    fields = dict(rsu_id="rsu-1", seq=7, capture_time_ns=T0, publish_time_ns=T0 + 95_000_000) | changes
    return ObjectListHeader(**fields)


def car(i: int = 0, **changes) -> ObjectState:
    fields = dict(id=i, cls=ObjectClass.CAR, x=10.0 + i, y=-3.0, length=4.5, width=1.8, yaw=0.3, vx=12.0) | changes
    return ObjectState(**fields)


def object_list(n: int) -> ObjectList:
    rng = np.random.default_rng(1)
    objects = tuple(
        car(i, x=rng.uniform(-300, 300), y=rng.uniform(-300, 300), yaw=rng.uniform(-3, 3), vx=rng.uniform(-20, 20))
        for i in range(n)
    )
    return ObjectList(header=header(), objects=objects)


def decode_fails(data: bytes, model, error: type[CodecError]) -> CodecError:
    with pytest.raises(error) as info:
        decode(data, model)
    return info.value


def decode_safely(data: bytes) -> None:
    """Decoding hostile bytes as any model may only succeed or raise CodecError."""
    for model in MODELS:
        try:
            decode(data, model)
        except CodecError as exc:
            assert exc.reason in {"too_large", "malformed", "version", "wrong_type", "invalid"}
            assert str(exc)


# ---------------------------------------------------------------- properties


@FAST
@given(messages)
def test_round_trip_is_exact(msg) -> None:
    data = encode(msg)
    back = decode(data, type(msg))
    assert back == msg
    assert encode(back) == data


@FAST
@given(st.binary(max_size=512))
def test_random_bytes_raise_only_codec_errors(data: bytes) -> None:
    decode_safely(data)


@FAST
@given(messages, st.data())
def test_mutated_messages_raise_only_codec_errors(msg, data) -> None:
    raw = bytearray(encode(msg))
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(raw) - 1))
        raw[i] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(raw)))
    decode_safely(bytes(raw))
    decode_safely(bytes(raw[:cut]))


plain = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**64), 2**64) | st.floats()
    | st.text(max_size=8) | st.binary(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


@FAST
@given(st.sampled_from(MODELS), st.dictionaries(st.sampled_from(["objects", "header", "x", "seq", "rsus"]), plain))
def test_well_formed_envelopes_with_junk_bodies_raise_only_codec_errors(model, body) -> None:
    try:
        data = envelope(model.TYPE, body)
    except (OverflowError, TypeError):
        return  # not representable in msgpack at all
    decode_safely(data)


# ---------------------------------------------------------------- envelope


def test_wrong_schema_version_is_rejected() -> None:
    body = body_of(encode(object_list(2)))
    err = decode_fails(envelope(ObjectList.TYPE, body, version=SCHEMA_VERSION + 1), ObjectList, SchemaVersionError)
    assert err.reason == "version" and f"version {SCHEMA_VERSION + 1}" in str(err)
    decode_fails(envelope(ObjectList.TYPE, body, version="1"), ObjectList, MalformedMessage)


def test_version_is_checked_before_type_tag() -> None:
    decode_fails(envelope("time_reply", {}, version=99), ObjectList, SchemaVersionError)


def test_wrong_type_tag_is_rejected() -> None:
    data = encode(TimeRequest(obu_id="car-1", seq=1, t1_ns=T0))
    err = decode_fails(data, TimeReply, WrongMessageType)
    assert err.reason == "wrong_type" and "time_request" in str(err) and "time_reply" in str(err)


@pytest.mark.parametrize(
    "value",
    [[1, 2], {"v": 1, "t": "object_list"}, {"v": 1, "t": "object_list", "d": {}, "x": 0}, 3],
)
def test_wrong_envelope_shape_is_malformed(value) -> None:
    err = decode_fails(msgpack.packb(value), ObjectList, MalformedMessage)
    assert err.reason == "malformed"


def test_body_that_is_not_a_map_is_malformed() -> None:
    decode_fails(envelope(ObjectList.TYPE, [1, 2]), ObjectList, MalformedMessage)


def test_trailing_bytes_and_garbage_are_malformed() -> None:
    data = encode(object_list(1))
    decode_fails(data + b"\x00", ObjectList, MalformedMessage)
    decode_fails(data[:-1], ObjectList, MalformedMessage)
    decode_fails(b"", ObjectList, MalformedMessage)
    decode_fails(b"\xc1", ObjectList, MalformedMessage)


def test_hostile_container_lengths_are_rejected_without_allocation() -> None:
    # 1000 nested arrays each claiming 2**31 elements: tiny payload, huge pre-allocation if unbounded.
    decode_fails(b"\xdd\x7f\xff\xff\xff" * 1000, ObjectList, MalformedMessage)
    decode_fails(b"\x91" * 5000, ObjectList, MalformedMessage)


# ---------------------------------------------------------------- size


def test_oversize_encode_is_rejected() -> None:
    msg = object_list(50)
    with pytest.raises(MessageTooLarge) as info:
        encode(msg, max_bytes=100)
    assert info.value.reason == "too_large" and "limit is 100" in str(info.value)


def test_oversize_decode_is_rejected_before_unpacking() -> None:
    decode_fails(b"\xc1" * (MAX_MESSAGE_BYTES + 1), ObjectList, MessageTooLarge)
    data = encode(object_list(5))
    with pytest.raises(MessageTooLarge):
        decode(data, ObjectList, max_bytes=len(data) - 1)
    assert decode(data, ObjectList, max_bytes=len(data)) == object_list(5)


def test_full_object_list_fits_the_default_limit() -> None:
    msg = ObjectList(header=header(), objects=tuple(car(i) for i in range(MAX_OBJECTS)))
    assert decode(encode(msg), ObjectList) == msg


# ---------------------------------------------------------------- model rules on decode


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_field_is_invalid(bad: float) -> None:
    body = body_of(encode(EgoPose(vehicle_id="car-1", t_ns=T0, x=1.0, y=2.0))) | {"x": bad}
    err = decode_fails(envelope(EgoPose.TYPE, body), EgoPose, InvalidMessage)
    assert err.reason == "invalid" and err.field == "x" and "x:" in str(err)


def test_non_finite_object_value_is_rejected_when_the_columns_are_built() -> None:
    bad = (car(0), car(1).model_copy(update={"vx": math.nan}))  # model_copy skips validation
    with pytest.raises(InvalidMessage) as info:
        ObjectColumns.from_states(bad)
    assert info.value.field == "objects.1.vx"
    with pytest.raises(ValueError, match="objects.1.vx"):
        ObjectList(header=header(), objects=bad)


def test_unknown_key_in_body_is_invalid() -> None:
    body = body_of(encode(EgoPose(vehicle_id="car-1", t_ns=T0, x=1.0, y=2.0))) | {"speed_limit": 50}
    err = decode_fails(envelope(EgoPose.TYPE, body), EgoPose, InvalidMessage)
    assert err.field == "speed_limit"


def test_extra_positional_field_of_an_object_list_is_malformed() -> None:
    # object lists carry their fields by position: an unknown one is an entry too many
    body = body_of(encode(object_list(1))) | {"speed_limit": 50}
    assert "at most 1 fields" in str(decode_fails(envelope(ObjectList.TYPE, body), ObjectList, MalformedMessage))
    body = body_of(encode(object_list(1)))
    body["header"]["extra"] = 1
    decode_fails(envelope(ObjectList.TYPE, body), ObjectList, MalformedMessage)


@pytest.mark.parametrize("t_ns", [0, 86_400 * 10**9, 7_258_118_400 * 10**9])  # 1970-01-01, 1970-01-02, 2200-01-01
def test_absurd_timestamp_is_invalid(t_ns: int) -> None:
    body = {"obu_id": "car-1", "seq": 1, "t1_ns": t_ns}
    err = decode_fails(envelope(TimeRequest.TYPE, body), TimeRequest, InvalidMessage)
    assert err.field == "t1_ns"
    body = body_of(encode(object_list(1)))
    body["header"]["capture_time_ns"] = t_ns
    assert decode_fails(envelope(ObjectList.TYPE, body), ObjectList, InvalidMessage).field.startswith("header")


def test_publish_before_capture_is_invalid() -> None:
    body = body_of(encode(object_list(1)))
    body["header"]["publish_time_ns"] = body["header"]["capture_time_ns"] - 1
    err = decode_fails(envelope(ObjectList.TYPE, body), ObjectList, InvalidMessage)
    assert err.field == "header" and "publish_time_ns" in str(err)


def test_out_of_model_range_column_value_is_invalid() -> None:
    body = body_of(encode(object_list(3)))
    body["objects"]["refs"][present_index("x", body)] = 2**31 - 1  # 21474836 m: outside the model's +-1e6 m
    err = decode_fails(envelope(ObjectList.TYPE, body), ObjectList, InvalidMessage)
    assert err.field == "objects.0.x"


def test_unknown_class_code_is_invalid() -> None:
    body = body_of(encode(object_list(1)))
    body["objects"]["refs"][present_index("cls", body)] = 200
    assert decode_fails(envelope(ObjectList.TYPE, body), ObjectList, InvalidMessage).field == "objects.0.cls"


# ---------------------------------------------------------------- columns


def test_truncated_column_is_malformed() -> None:
    body = body_of(encode(object_list(4)))
    rows = body["objects"]["rows"]
    body["objects"]["rows"] = rows[:-1]
    err = decode_fails(envelope(ObjectList.TYPE, body), ObjectList, MalformedMessage)
    assert f"rows are {len(rows) - 1} bytes, 4 objects of {len(rows) // 4} bytes expected" in str(err)


@pytest.mark.parametrize("change", ["missing", "extra", "n_negative", "n_str", "not_bytes", "not_array", "wide",
                                    "flag", "refs", "scale", "beyond"])
def test_bad_column_layout_is_malformed(change: str) -> None:
    body = body_of(encode(object_list(2)))
    cols = body["objects"]
    if change == "missing":
        cols["present"] &= ~(1 << COLUMN["x"])  # a required column
    elif change == "extra":
        cols["colour"] = b"\x00\x00"
    elif change == "n_negative":
        cols["n"] = -1
    elif change == "n_str":
        cols["n"] = "2"
    elif change == "not_bytes":
        cols["rows"] = [0, 1]
    elif change == "wide":
        cols["widths"] = bytes([49]) + cols["widths"][1:]
    elif change == "flag":
        cols["widths"] = bytes([cols["widths"][0] | 0x80]) + cols["widths"][1:]
    elif change == "refs":
        cols["refs"] = cols["refs"][:-1]
    elif change == "scale":
        cols["widths"] = bytes([cols["widths"][0] | 0x40]) + cols["widths"][1:]
        cols["scales"] = [2**47]
    elif change == "beyond":
        cols["present"] |= 1 << 22  # sources: not a column of an ObjectList
    else:
        body["objects"] = {"objects": list(cols.values())}
    decode_fails(envelope(ObjectList.TYPE, body), ObjectList, MalformedMessage)


def test_object_count_above_max_is_invalid() -> None:
    n = MAX_OBJECTS + 1
    body = body_of(encode(object_list(1)))
    body["objects"] |= {"n": n, "rows": body["objects"]["rows"] * n}
    err = decode_fails(envelope(ObjectList.TYPE, body), ObjectList, InvalidMessage)
    assert err.field == "objects" and str(MAX_OBJECTS) in str(err)
    with pytest.raises(InvalidMessage):
        ObjectColumns.from_states((car(0),) * n)


@pytest.mark.parametrize(("field", "value"), [("x", 3e7), ("id", 2**32), ("id", -1), ("vx", 400.0), ("length", -1.0)])
def test_unrepresentable_value_is_rejected_not_wrapped(field: str, value: float) -> None:
    bad = car(0).model_copy(update={field: value})  # model_copy skips validation
    with pytest.raises(InvalidMessage) as info:
        ObjectColumns.from_states((bad,))
    assert info.value.field == f"objects.0.{field}"


def test_columns_are_codes_with_per_message_widths() -> None:
    msg = ObjectList(header=header(), objects=(car(3, x=-1.25, yaw=-math.pi, confidence=0.5, age_s=2.5),
                                               car(4, x=-1.05, yaw=-math.pi, confidence=0.5, age_s=2.5)))
    body = body_of(encode(msg))
    cols = body["objects"]
    assert cols["n"] == 2
    # default columns (z, height, ax, ay, yaw_rate, covariances) are left out
    assert not cols["present"] >> COLUMN["z"] & 1 and not cols["present"] >> COLUMN["cov_vxx"] & 1
    ref = {name: cols["refs"][present_index(name, body)] for name in ("id", "x", "yaw", "confidence", "age_s")}
    assert ref == {"id": 3, "x": -125, "yaw": -1800, "confidence": 50, "age_s": 2500}
    width = {name: cols["widths"][present_index(name, body)] for name in ("id", "x", "yaw")}
    assert width == {"id": 1, "x": 0x40 | 1, "yaw": 0}  # x: codes -125, -105 = ref + {0, 1} * 20
    assert cols["scales"] == [20]
    assert len(cols["rows"]) == 2  # 2 bits per object (id, x) in one byte each


def test_fused_list_carries_sources_column() -> None:
    obj = FusedObject(**dict(car(1)), sources=3)
    msg = FusedObjectList(vehicle_id="car-1", seq=1, cycle_time_ns=T0, publish_time_ns=T0, objects=(obj,))
    body = body_of(encode(msg))
    assert body["objects"]["refs"][present_index("sources", body)] == 3
    assert decode(encode(msg), FusedObjectList).objects[0].sources == 3


def test_yaw_rate_limit_round_trips() -> None:
    obj = car(0, yaw_rate=30.0)
    msg = ObjectList(header=header(), objects=(obj,))
    assert decode(encode(msg), ObjectList) == msg


@pytest.mark.parametrize("yaw", [-math.pi, math.pi, 3 * math.pi, -100.0, 100.0, math.pi - 1e-12, -math.pi + 1e-12])
def test_yaw_edges_round_trip(yaw: float) -> None:
    msg = FusedObjectList(
        vehicle_id="car-1", seq=1, cycle_time_ns=T0, publish_time_ns=T0, ego_yaw=yaw,
        objects=(FusedObject(**dict(car(0, yaw=yaw))),),
    )
    back = decode(encode(msg), FusedObjectList)
    assert back == msg and -math.pi <= back.objects[0].yaw < math.pi


def test_columnar_encoding_is_compact() -> None:
    msg = object_list(200)
    data = encode(msg)
    plain_size = len(msgpack.packb(msg.model_dump(mode="python")))
    assert len(data) < plain_size / 3
    assert decode(data, ObjectList) == msg


def test_empty_object_list_round_trips() -> None:
    msg = ObjectList(header=header())
    assert decode(encode(msg), ObjectList) == msg


def test_encode_and_decode_reject_non_messages() -> None:
    with pytest.raises(TypeError):
        encode({"v": 1})  # type: ignore[arg-type]
    with pytest.raises(TypeError):
        decode("not bytes", ObjectList)  # type: ignore[arg-type]


def test_decode_accepts_bytearray_and_memoryview() -> None:
    data = encode(object_list(2))
    assert decode(bytearray(data), ObjectList) == decode(memoryview(data), ObjectList) == object_list(2)


def test_importing_schemas_does_not_import_zenoh() -> None:
    src = Path(__file__).resolve().parents[2] / "src"
    code = "import sys, schemas; assert 'zenoh' not in sys.modules, 'zenoh imported'"
    env = os.environ | {"PYTHONPATH": str(src)}
    subprocess.run([sys.executable, "-c", code], check=True, env=env)


def test_prediction_list_needs_one_matching_path_per_object() -> None:
    path = PredictedPath(id=0, x=(1.0, 2.0), y=(0.0, 0.0), yaw=(0.0, 0.0))
    ok = PredictionList(header=header(), objects=(car(0),), paths=(path,))
    assert decode(encode(ok), PredictionList) == ok
    assert ok.horizon_ns == 2 * ok.step_ns
    with pytest.raises(ValueError, match="paths"):
        PredictionList(header=header(), objects=(car(0),), paths=())
    with pytest.raises(ValueError, match="differs"):
        PredictionList(header=header(), objects=(car(1),), paths=(path,))
    with pytest.raises(ValueError, match="one entry per step"):
        PredictedPath(id=0, x=(1.0,), y=(), yaw=())


def test_velocity_covariance_round_trips_and_defaults_to_unknown() -> None:
    from v2i.fusion.wire import objects_from_states, states_from_objects

    plain = objects_from_states(decode(encode(ObjectList(header=header(), objects=(car(1),))), ObjectList).objects)
    assert not plain.velocity_known()[0]  # a sender that states no velocity covariance
    tracked = plain.with_(cov_vxy=np.array([[[0.25, -0.05], [-0.05, 0.16]]]))
    msg = ObjectList(header=header(), objects=states_from_objects(tracked))
    back = objects_from_states(decode(encode(msg), ObjectList).objects)
    np.testing.assert_allclose(back.cov_vxy, tracked.cov_vxy, atol=1e-12)
    assert back.velocity_known()[0]


def test_an_object_section_is_packed_once_and_encodes_as_packed() -> None:
    """encode writes the columns' wire_section (packed once per immutable ObjectColumns): the very
    bytes of the envelope with a fresh pack_objects, and a prediction list carrying a list's
    columns shares that list's section."""
    from schemas.codec import _positional
    from schemas.object_wire import pack_objects, wire_section

    msg = object_list(40)
    fresh = [SCHEMA_VERSION, LIST_TAGS[ObjectList.TYPE], _positional(msg), pack_objects(msg.objects)]
    assert encode(msg) == msgpack.packb(fresh, use_bin_type=True)
    pred = PredictionList(header=msg.header, objects=msg.objects,
                          paths=tuple(PredictedPath(id=o.id) for o in msg.objects))
    assert wire_section(pred.objects) is wire_section(msg.objects)
    assert decode(encode(pred), PredictionList).objects == msg.objects


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(prediction_lists())
def test_predicted_paths_encode_as_their_model_dump(msg) -> None:
    """encode writes each predicted path as a plain {id, x, y, yaw} map: the very bytes of the
    envelope built with pydantic's model_dump (the path model has exactly those fields)."""
    from schemas.codec import _layout, _positional
    from schemas.object_wire import pack_objects

    assert list(PredictedPath.model_fields) == ["id", "x", "y", "yaw"]
    want = []
    for name, default, nested in _layout(PredictionList):
        value = getattr(msg, name)
        if value == default and type(value) is type(default):
            want.append(None)
        elif nested is not None:
            want.append(_positional(value))
        elif isinstance(value, tuple):
            want.append([v.model_dump(mode="python") for v in value])
        else:
            want.append(value)
    while want and want[-1] is None:
        want.pop()
    envelope = [SCHEMA_VERSION, LIST_TAGS[PredictionList.TYPE], want, pack_objects(msg.objects)]
    assert encode(msg) == msgpack.packb(envelope, use_bin_type=True)
