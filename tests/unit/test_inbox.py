"""obu_service.inbox: envelope -> header -> admission -> body -> pipeline, admitted once per message."""

from collections import Counter

import numpy as np
import pytest

from v2i.core.objects import ObjectArray
from v2i.fusion.wire import states_from_objects
from v2i.offline.decode_memo import DecodeMemo
from v2i.security.envelope import Signer
from v2i.security.site import memory_site
from obu_service import inbox as inbox_module
from obu_service.admission import Admission
from obu_service.inbound_security import InboundSecurity, make_verifier
from obu_service.inbox import Inbox, Outcome
from obu_service.pipeline import ObuPipeline, ObuPipelineConfig
from rsu_service.pipeline import answer_time_request
from schemas import keys
from schemas.codec import encode
from schemas.list_wire import encode_list, list_key
from schemas.messages import ObjectList, ObjectListHeader, PredictedPath, PredictionList

T0 = 1_767_225_600 * 10**9
THETA = 350_000_000  # RSU clock - OBU clock
MS = 1_000_000
RSU = "rsu1"


def objs(n: int) -> ObjectArray:
    xy = np.column_stack([np.arange(n) * 5.0, np.full(n, -20.0)])
    return ObjectArray(ids=np.arange(1, n + 1), cls=np.ones(n, int), xy=xy, z=np.full(n, 0.75),
                       lwh=np.tile([4.5, 1.8, 1.5], (n, 1)), yaw=np.zeros(n), vxy=np.zeros((n, 2)))


def header(capture_obu_ns: int, seq: int = 0) -> ObjectListHeader:
    return ObjectListHeader(rsu_id=RSU, seq=seq, capture_time_ns=capture_obu_ns + THETA,
                            publish_time_ns=capture_obu_ns + THETA + 50 * MS)


def rsu_list(capture_obu_ns: int, n: int = 2, seq: int = 0) -> ObjectList:
    return ObjectList(header=header(capture_obu_ns, seq), objects=states_from_objects(objs(n)))


def synced(policy: str = "off", trust=None, **cfg) -> tuple[ObuPipeline, Inbox]:
    """A pipeline that knows the RSU's clock, and its inbox (``policy`` off: unsigned bytes pass)."""
    p = ObuPipeline(ObuPipelineConfig(**{"fusion": "iou-merge", **cfg}))
    reply = answer_time_request(p.make_time_request(T0), RSU, T0 + 5 * MS + THETA, T0 + 5 * MS + THETA)
    p.on_time_reply(reply, T0 + 10 * MS)
    security = InboundSecurity(make_verifier(trust, policy, 5.0), p.clock_offset, p.reject)
    return p, Inbox(p, security)


def counting(monkeypatch, owner, name: str) -> Counter:
    """Counts the calls of ``owner.name`` (still called)."""
    calls: Counter = Counter()
    fn = getattr(owner, name)

    def counted(*args, **kwargs):
        calls[name] += 1
        return fn(*args, **kwargs)

    monkeypatch.setattr(owner, name, counted)
    return calls


def test_a_list_is_admitted_once_and_taken_as_admitted(monkeypatch):
    p, inbox = synced()
    calls = counting(monkeypatch, Admission, "lists")
    t = T0 + 1_000 * MS
    assert inbox.take("rsu", keys.rsu_objects(RSU), encode(rsu_list(t - 100 * MS)), t) is Outcome.READ
    assert calls["lists"] == 1
    assert p.metrics(t).rsus[0].messages_accepted == 1 and not p.rejected


def test_a_refused_header_leaves_the_objects_undecoded(monkeypatch):
    p, inbox = synced(max_objects_per_list=4)
    calls = counting(monkeypatch, inbox_module, "from_body")
    t = T0 + 1_000 * MS
    assert inbox.take("rsu", keys.rsu_objects(RSU), encode(rsu_list(t - 100 * MS, n=5)), t) is Outcome.READ
    assert calls["from_body"] == 0 and p.rejected == {"too_many_objects": 1}
    inbox.take("rsu", keys.rsu_objects(RSU), encode(rsu_list(t - 100 * MS, n=4, seq=1)), t)
    assert calls["from_body"] == 1 and p.metrics(t).rsus[0].messages_accepted == 1


def test_the_inbox_ends_as_the_pipeline_entry_for_decoded_messages():
    """The same list through the inbox and through ``on_rsu_message``: the same state and counters."""
    t = T0 + 1_000 * MS
    msgs = [rsu_list(t - 100 * MS, seq=0), rsu_list(t - 100 * MS, seq=0), rsu_list(t + 900 * MS, seq=1)]
    p, inbox = synced()
    for msg in msgs:
        inbox.take("rsu", keys.rsu_objects(RSU), encode(msg), t)
    q, _ = synced()
    for msg in msgs:
        q.on_rsu_message(msg, t)
    assert p.rejected == q.rejected == {"duplicate": 1, "future_timestamp": 1}
    assert p.metrics(t) == q.metrics(t)


def test_paths_are_admitted_from_their_header_and_counts():
    p, inbox = synced(max_path_points=100)
    t = T0 + 1_000 * MS
    path = PredictedPath(id=1, x=[5.0] * 101, y=[-20.0] * 101, yaw=[0.0] * 101)
    paths = PredictionList(header=header(t - 100 * MS), objects=states_from_objects(objs(1)), paths=(path,))
    inbox.take("predictions", keys.rsu_predictions(RSU), encode(paths), t)
    assert p.rejected == {"too_many_path_points": 1}
    kept = paths.model_copy(update={"paths": (PredictedPath(id=1, x=[5.0] * 100, y=[-20.0] * 100, yaw=[0.0] * 100),)})
    inbox.take("predictions", keys.rsu_predictions(RSU), encode(kept), t)
    assert p._rsus.get(RSU).predictions == kept


@pytest.mark.parametrize("wire", ["cpm", "sdsm"])
def test_a_standard_list_is_read_whole_and_admitted_once(monkeypatch, wire):
    p, inbox = synced()
    calls = counting(monkeypatch, Admission, "lists")
    t = T0 + 1_000 * MS
    data = encode_list(rsu_list(t - 100 * MS), wire)
    assert inbox.take(wire, list_key(wire, RSU), data, t) is Outcome.READ
    assert calls["lists"] == 1 and p.metrics(t).rsus[0].messages_accepted == 1


def test_outcomes_dropped_unreadable_and_counted_details():
    trust, ids = memory_site(T0 - 86_400 * 10**9, [RSU], [])
    p, inbox = synced("strict", trust)
    t = T0 + 1_000 * MS
    assert inbox.take("rsu", keys.rsu_objects(RSU), encode(rsu_list(t - 100 * MS)), t) is Outcome.DROPPED
    signed = Signer(ids[RSU]).sign(b"\x94garbage", t - 20 * MS + THETA, keys.rsu_objects(RSU))
    assert inbox.take("rsu", keys.rsu_objects(RSU), signed, t) is Outcome.UNREADABLE
    reason = next(r for r in p.rejected if not r.startswith("security_"))
    assert p.rejected["security_unsigned"] == 1 and reason in inbox.details
    assert inbox.details[reason].startswith(f"rsu on {keys.rsu_objects(RSU)}: ")


def test_a_broadcast_is_read_once_for_all_its_receivers():
    """The offline runner's receivers share a DecodeMemo: one header read and one body decode per bytes."""
    memo = DecodeMemo()
    t = T0 + 1_000 * MS
    data = encode(rsu_list(t - 100 * MS))
    receivers = []
    for _ in range(3):
        p, inbox = synced()
        inbox.memo = memo
        inbox.take("rsu", keys.rsu_objects(RSU), data, t)
        receivers.append(p)
    assert memo.hits == 2
    first, *others = (p._rsus.get(RSU).frames[0].objects for p in receivers)
    assert all(np.array_equal(o.xy, first.xy) for o in others)


def test_stage_latencies_are_recorded_when_asked():
    observed: list[str] = []

    class Recorder:
        def observe_ns(self, stage, start_ns, end_ns):
            observed.append(stage)

    p, inbox = synced()
    inbox.latency, inbox.ticks = Recorder(), iter(range(0, 10**9, 1000)).__next__
    t = T0 + 1_000 * MS
    inbox.take("rsu", keys.rsu_objects(RSU), encode(rsu_list(t - 100 * MS)), t)
    assert observed == ["verify", "decode", "ingest", "rsu_to_obu"]
