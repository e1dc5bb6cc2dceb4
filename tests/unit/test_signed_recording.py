"""Signed RSU messages (``v2i.security.envelope``) in recordings: kept as on the wire, read and
replayed from inside their envelopes (``telemetry.mcap_*``, ``v2i.telemetry.replayer``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mcap.reader import make_reader

from schemas.codec import decode, encode
from schemas.messages import ObjectList, ObjectListHeader, TimeReply
from v2i.security.envelope import PREFIX, Signer, unwrap
from v2i.security.site import memory_site
from v2i.telemetry import mcap_channels as mc
from v2i.telemetry.mcap_reader import Recording
from v2i.telemetry.mcap_writer import RunWriter
from v2i.telemetry.time_shift import shift_message, shift_payload
from v2i.telemetry.replayer import Replayer

T_NS = 1_795_545_547_592_119_513
KEY = "v2x/rsu/rsu1/objects"
TIME_KEY = "v2x/rsu/rsu1/time"


@pytest.fixture(scope="module")
def signer() -> Signer:
    _, ids = memory_site(T_NS, ["rsu1"], ["ego"])
    return Signer(ids["rsu1"])


def object_list(t_ns: int, seq: int = 3) -> ObjectList:
    header = ObjectListHeader(rsu_id="rsu1", seq=seq, capture_time_ns=t_ns, publish_time_ns=t_ns + 90_000_000)
    return ObjectList(header=header, objects=[{"id": 7, "x": 10.0, "y": -3.0, "length": 4.5, "width": 1.8}])


def test_unwrap_gives_the_payload_of_an_envelope_else_the_bytes_unchanged(signer):
    payload = encode(object_list(T_NS))
    assert unwrap(signer.sign(payload, T_NS, KEY)) == payload
    assert unwrap(payload) == payload
    broken = PREFIX + b"\x00" * 20  # the envelope prefix, then nothing that parses
    assert unwrap(broken) == broken
    rng = np.random.default_rng(3)
    for _ in range(300):  # never raises
        data = PREFIX + rng.integers(0, 256, size=int(rng.integers(0, 120)), dtype=np.uint8).tobytes()
        assert isinstance(unwrap(data), bytes)


def test_classify_looks_inside_an_envelope(signer):
    signed = signer.sign(encode(object_list(T_NS)), T_NS, KEY)
    kind = mc.classify(KEY, signed)
    assert (kind.name, kind.model, kind.signed) == ("object_list", ObjectList, True)
    assert kind.message_encoding == "v2i-signed+v2i-msgpack" and kind.label == "signed-object_list"
    plain = mc.classify(KEY, encode(object_list(T_NS)))
    assert not plain.signed and plain.message_encoding == mc.V2I_ENCODING
    cpm = mc.classify("v2x/rsu/rsu1/cpm", signer.sign(b"\x01\x02", T_NS, "v2x/rsu/rsu1/cpm"))
    assert (cpm.name, cpm.message_encoding, cpm.signed) == ("cpm", "v2i-signed+uper", True)


def _signed_recording(path, signer: Signer) -> tuple[list, bytes]:
    """Ten signed lists, an unsigned (injected) list on the same key, twenty signed time replies."""
    writer = RunWriter(path)
    lists = []
    for i in range(10):
        t_ns = T_NS + i * 100_000_000
        data = signer.sign(encode(object_list(t_ns, seq=i)), t_ns + 90_000_000, KEY)
        lists.append(data)
        writer.write("vehicle", KEY, data, t_ns + 120_000_000)
    injected = encode(object_list(T_NS + 50_000_000, seq=99))
    writer.write("vehicle", KEY, injected, T_NS + 130_000_000)
    for i in range(20):  # theta = rsu - host = 25 ms, 1 ms each way
        t1 = T_NS + i * 100_000_000
        reply = TimeReply(rsu_id="rsu1", seq=i, t1_ns=t1, t2_ns=t1 + 26_000_000, t3_ns=t1 + 26_000_000)
        writer.write("rsu", TIME_KEY, signer.sign(encode(reply), reply.t3_ns, TIME_KEY), t1 + 2_000_000)
    writer.close()
    return lists, injected


def test_a_signed_recording_keeps_the_envelopes_and_reads_inside_them(tmp_path, signer):
    path = tmp_path / "signed.mcap"
    lists, injected = _signed_recording(path, signer)
    recording = Recording(path)
    samples = list(recording.samples("vehicle", KEY))
    assert [s.payload for s in samples if s.signed] == lists  # byte for byte: the evidence
    assert [s.payload for s in samples if not s.signed] == [injected]
    assert [decode(s.content, ObjectList).header.seq for s in samples if s.signed] == list(range(10))
    channels = {(c.key, c.kind, c.signed): c.topic for c in recording.channels.values()}
    assert channels[(KEY, "object_list", True)] == f"/vehicle/{KEY}"
    assert channels[(KEY, "object_list", False)] == f"/vehicle/{KEY}~object_list"
    exchanges = recording.exchanges()["rsu1"]
    assert len(exchanges) == 20 and {e.offset_ns for e in exchanges} == {25_000_000}
    with open(path, "rb") as f:  # the Foxglove mirror is made from the payload inside
        reader = make_reader(f)
        topics = {c.topic: c for c in reader.get_summary().channels.values()}
        assert topics[f"/vehicle/{KEY}"].message_encoding == "v2i-signed+v2i-msgpack"
        scenes = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=[f"/vehicle/{KEY}/scene"])]
    assert len(scenes) == 10 and scenes[0]["entities"][0]["id"] == "rsu-rsu1-7"


def test_replay_republishes_signed_samples_shifted_and_unsigned(tmp_path, signer):
    path = tmp_path / "signed.mcap"
    lists, injected = _signed_recording(path, signer)
    replayer = Replayer(Recording(path), "vehicle")
    shift_ns = replayer.align(T_NS + 60_000_000_000) - replayer.l0_ns
    published = [replayer._shifted(s, 0, shift_payload) for s in replayer.recording.samples("vehicle", KEY)]
    assert not any(p.startswith(PREFIX) for p in published) and len(published) == 11
    assert replayer.counts["envelopes_removed"] == 10 and replayer.counts["unshifted"] == 0
    assert decode(published[0], ObjectList) == shift_message(decode(unwrap(lists[0]), ObjectList), shift_ns)
    assert decode(published[1], ObjectList) == shift_message(decode(injected, ObjectList), shift_ns)
    assert replayer.clocks["rsu1"].offset_at(T_NS + 500_000_000) == 25_000_000  # from inside the envelopes
