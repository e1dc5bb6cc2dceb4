"""Recording and replay, the pure parts: stamp shifting, the recorded RSU clock, the MCAP round trip."""

from __future__ import annotations

import json

import msgpack
import numpy as np
import pytest
from mcap.reader import make_reader

from v2i.offline.recorded_run import run_metadata, spec_of
from v2i.offline.spec import RunSpec
from schemas import list_wire
from schemas.codec import decode, encode
from schemas.messages import (SCHEMA_VERSION, FusedObjectList, ObjectList, ObjectListHeader, ObuMetrics, PredictedPath,
                              PredictionList, TimeReply)
from v2i.telemetry import mcap_channels as mc
from v2i.telemetry.mcap_reader import Recording, RecordingError, key_matches
from v2i.telemetry.mcap_writer import RunWriter
from v2i.telemetry.time_shift import Exchange, RsuClockTrack, round_shift_ns, shift_message, shift_payload

T_NS = 1_795_545_547_592_119_513
OBJ = {"id": 7, "x": 10.0, "y": -3.0, "length": 4.5, "width": 1.8, "yaw": 0.5}


def object_list(t_ns: int = T_NS, prediction_ns: int = 0) -> ObjectList:
    header = ObjectListHeader(rsu_id="rsu1", seq=3, capture_time_ns=t_ns, publish_time_ns=t_ns + 90_000_000,
                              prediction_ns=prediction_ns)
    return ObjectList(header=header, objects=[OBJ])


def test_shift_moves_every_stamp_and_no_duration():
    shifted = shift_message(object_list(prediction_ns=200_000_000), 5_000_000_000)
    assert shifted.header.capture_time_ns == T_NS + 5_000_000_000
    assert shifted.header.publish_time_ns == T_NS + 90_000_000 + 5_000_000_000
    assert shifted.header.prediction_ns == 200_000_000  # a duration, not a stamp
    assert shifted.objects == object_list().objects
    reply = shift_message(TimeReply(rsu_id="r", seq=1, t1_ns=T_NS, t2_ns=T_NS + 5, t3_ns=T_NS + 9), -7)
    assert (reply.t1_ns, reply.t2_ns, reply.t3_ns) == (T_NS - 7, T_NS - 2, T_NS + 2)
    metrics = shift_message(ObuMetrics(vehicle_id="ego", t_ns=T_NS, cycles=4), 1)
    assert metrics.t_ns == T_NS + 1 and metrics.cycles == 4


def test_shift_payload_v2i_round_trips_through_the_codec():
    paths = PredictionList(header=object_list().header, objects=[OBJ],
                           paths=[PredictedPath(id=7, x=[11.0, 12.0], y=[-3.0, -3.0], yaw=[0.0, 0.0])])
    for msg in (object_list(), paths):
        data = shift_payload(msg.TYPE, type(msg), encode(msg), 2_000_000)
        assert decode(data, type(msg)) == shift_message(msg, 2_000_000)
    raw = encode(object_list())
    assert shift_payload("object_list", ObjectList, raw, 0) is raw
    with pytest.raises(ValueError):
        shift_payload("json", None, b"{}", 1_000_000)


def test_shift_payload_cpm_is_exact_for_whole_milliseconds():
    original = list_wire.decode_list(list_wire.encode_list(object_list(), "cpm"), "cpm", "rsu1")
    data = shift_payload("cpm", None, list_wire.encode_list(original, "cpm"), 3_000_000_000, "rsu1")
    shifted = shift_message(original, 3_000_000_000)
    # a CPM's sequence number comes from its reference time (8 a ms): it moves with the shift
    expected = shifted.model_copy(update={"header": shifted.header.model_copy(update={"seq": original.header.seq + 8 * 3000})})
    assert list_wire.decode_list(data, "cpm", "rsu1") == expected


def test_round_shift_is_whole_milliseconds():
    assert round_shift_ns(1_499_999) == 1_000_000
    assert round_shift_ns(-2_600_000) == -3_000_000
    assert round_shift_ns(16_334_212_345) % 1_000_000 == 0


def _exchanges(theta_of, n: int = 200, rng=None, slow_every: int = 10) -> list[Exchange]:
    """Exchanges every 100 ms: symmetric 1 ms paths with 0.2 ms jitter, every ``slow_every``-th
    has a 40 ms asymmetric uplink (should be left out)."""
    rng = rng or np.random.default_rng(0)
    out = []
    for i in range(n):
        t1 = T_NS + i * 100_000_000
        up = 1_000_000 + int(rng.normal(0, 200_000)) + (40_000_000 if i % slow_every == 5 else 0)
        down = 1_000_000 + int(rng.normal(0, 200_000))
        t2 = t1 + up + theta_of(t1 + up)
        t3 = t2 + 50_000
        t4 = t1 + up + 50_000 + down
        out.append(Exchange(t1, t2, t3, t4))
    return out


def test_clock_track_follows_offset_drift_and_a_step():
    step_at = T_NS + 10_000_000_000

    def theta(h):  # 25 ms offset, 40 ppm drift, a 30 ms step at 10 s
        return 25_000_000 + round(40e-6 * (h - T_NS)) + (30_000_000 if h >= step_at else 0)

    track = RsuClockTrack(_exchanges(theta))
    assert track.dropped == 20 and track.used == 180
    for h in (T_NS + 2_000_000_000, T_NS + 8_000_000_000, step_at + 1_000_000_000, T_NS + 19_000_000_000):
        assert abs(track.offset_at(h) - theta(h)) < 300_000  # jitter 0.2 ms per path
    # the step's edge is kept: half a second either side is on its own level
    assert abs(track.offset_at(step_at - 500_000_000) - theta(step_at - 500_000_000)) < 300_000
    assert abs(track.offset_at(step_at + 500_000_000) - theta(step_at + 500_000_000)) < 300_000
    shift = 60_000_000_000
    t = T_NS + shift + 3_000_000_000
    assert track.rsu_time_ns(t, shift) == t + track.offset_at(t - shift)


def test_clock_track_without_exchanges():
    track = RsuClockTrack([])
    assert not track
    with pytest.raises(ValueError):
        track.offset_at(T_NS)


@pytest.mark.parametrize("pattern, key, match", [
    ("v2x/rsu/**", "v2x/rsu/rsu1/objects", True), ("v2x/rsu/**", "v2x/obu/ego/objects", False),
    ("v2x/rsu/*/objects", "v2x/rsu/a/objects", True), ("v2x/rsu/*/objects", "v2x/rsu/a/b/objects", False),
    ("**", "v2x/link/l/stats", True), ("v2x/**/stats", "v2x/link/l/stats", True), ("v2x/rsu", "v2x/rsu", True),
    ("v2x/**", "v2x", True), ("v2x/*", "v2x", False),
])
def test_key_matches(pattern, key, match):
    assert key_matches(pattern, key) is match


def test_classify_never_raises_on_random_bytes():
    rng = np.random.default_rng(1)
    for n in range(300):
        payload = rng.integers(0, 256, size=int(rng.integers(0, 64)), dtype=np.uint8).tobytes()
        assert mc.classify("v2x/rsu/x/objects", payload).name in (*mc.models_by_type(), "json", mc.UNKNOWN)
    # a msgpack bomb: a container claiming 2^31 entries is refused, not allocated
    assert mc.v2i_type(b"\xdd\x7f\xff\xff\xff") is None
    assert mc.classify("v2x/rsu/x/cpm", b"\x00").name == "cpm"


def _fused() -> FusedObjectList:
    return FusedObjectList(vehicle_id="ego", seq=1, cycle_time_ns=T_NS, publish_time_ns=T_NS + 30_000_000,
                           ego_x=100.0, ego_y=50.0, ego_yaw=np.pi / 2, objects=[{**OBJ, "sources": 3}])


def test_mcap_round_trip(tmp_path):
    path = tmp_path / "run.mcap"
    writer = RunWriter(path, derive_max_bytes=512)  # 400 objects: ~850 B
    big = ObjectList(header=object_list().header, objects=[{**OBJ, "id": i} for i in range(400)])
    # an obu_metrics envelope with a body that does not validate
    hostile = msgpack.packb({"v": SCHEMA_VERSION, "t": "obu_metrics", "d": {"vehicle_id": "ego", "cycles": -5}})
    samples = [("vehicle", "v2x/rsu/rsu1/objects", encode(object_list()), T_NS + 100),
               ("vehicle", "v2x/obu/ego/objects", encode(_fused()), T_NS + 200),
               ("vehicle", "v2x/obu/ego/metrics", encode(ObuMetrics(vehicle_id="ego", t_ns=T_NS, cycles=9)),
                T_NS + 300),
               ("link", "v2x/link/l/stats", json.dumps({"delivered": 3}).encode(), T_NS + 400),
               ("vehicle", "v2x/rsu/rsu1/objects", encode(big), T_NS + 500),
               ("vehicle", "v2x/obu/ego/metrics", hostile, T_NS + 600),
               ("rsu", "v2x/odd", b"\x00\x01 not a message", T_NS + 700)]
    for sample in samples:
        writer.write(*sample)
    writer.add_metadata("run", run_metadata(RunSpec(seed=4, duration_s=None), T_NS, 20.0, "ego", "rsu1"))
    writer.close()
    assert writer.messages == 7 and writer.skipped["oversized"] == 1
    assert sum(v for k, v in writer.skipped.items() if k.startswith("undecodable")) == 1, writer.skipped

    recording = Recording(path)
    assert recording.sides == ["link", "rsu", "vehicle"]
    got = [(s.side, s.key, s.payload, s.log_time_ns) for side in recording.sides for s in recording.samples(side)]
    assert sorted(got, key=lambda s: s[3]) == samples  # every sample raw, byte for byte, hostile ones too
    kinds = {c.topic: c.kind for c in recording.channels.values()}
    assert kinds["/vehicle/v2x/rsu/rsu1/objects"] == "object_list" and kinds["/rsu/v2x/odd"] == mc.UNKNOWN
    assert kinds["/link/v2x/link/l/stats"] == "json"
    spec = spec_of(recording.metadata["run"])
    assert spec.seed == 4 and spec.duration_s == 20.0

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()  # a closed file: summary and chunk index written
        assert summary is not None and summary.chunk_indexes
        topics = {c.topic: c for c in summary.channels.values()}
        schema = summary.schemas[topics["/vehicle/v2x/obu/ego/objects/scene"].schema_id]
        assert schema.name == "foxglove.SceneUpdate" and schema.encoding == "jsonschema"
        scenes = {ch.topic: json.loads(m.data) for _, ch, m in reader.iter_messages(topics=[
            "/vehicle/v2x/obu/ego/objects/scene", "/vehicle/v2x/obu/ego/metrics/json"])}
    cube = scenes["/vehicle/v2x/obu/ego/objects/scene"]["entities"][0]["cubes"][0]
    # base_link (10, -3) with the ego at (100, 50) heading +y: map (100 + 3, 50 + 10)
    position = cube["pose"]["position"]
    assert position["x"] == pytest.approx(103.0) and position["y"] == pytest.approx(60.0)
    assert scenes["/vehicle/v2x/obu/ego/metrics/json"]["cycles"] == 9
    assert topics["/vehicle/v2x/rsu/rsu1/objects"].message_encoding == mc.V2I_ENCODING


def test_recording_without_run_metadata_has_no_spec():
    with pytest.raises(ValueError, match="run metadata"):
        spec_of({})


def _small_recording(path) -> bytes:
    writer = RunWriter(path)
    for i in range(50):
        writer.write("vehicle", "v2x/rsu/rsu1/objects", encode(object_list(T_NS + i * 100_000_000)), T_NS + i)
    writer.close()
    return path.read_bytes()


@pytest.mark.parametrize("damage", ["random", "bit_flips", "zeros", "empty"])
def test_a_damaged_recording_is_a_clear_error(tmp_path, damage: str):
    """A recording is untrusted input: whatever is wrong with it is a RecordingError naming the file.
    (A file cut short is not damaged but not closed: test_recording_crash.)"""
    good = _small_recording(tmp_path / "good.mcap")
    rng = np.random.default_rng(7)
    data = bytearray(good)
    if damage == "random":
        data = bytearray(rng.integers(0, 256, 4000, dtype=np.uint8).tobytes())
    elif damage == "bit_flips":
        for i in rng.integers(0, len(data), 40):
            data[i] ^= 1 << int(rng.integers(0, 8))
    elif damage == "zeros":
        data[8:-8] = bytes(len(data) - 16)
    else:
        data = bytearray()
    path = tmp_path / "bad.mcap"
    path.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="bad.mcap"):
        recording = Recording(path)
        list(recording.samples("vehicle"))
