"""One answer per time query at the RSU, the first verified reply at the OBU (issue 32, item 2)."""

import pytest

from obu_service.inbound_security import InboundSecurity, make_verifier
from obu_service.inbox import Inbox, Outcome
from obu_service.pipeline import ObuPipeline, ObuPipelineConfig
from rsu_service.pipeline import answer_time_request
from rsu_service.time_answers import TimeAnswers
from schemas import keys
from schemas.codec import encode
from schemas.messages import TimeRequest
from v2i.clock.time_requests import TimeRequests
from v2i.security.envelope import Signer
from v2i.security.site import memory_site

T0 = 1_767_225_600 * 10**9
MS = 1_000_000
THETA = 350 * MS
RSU = "rsu1"


def test_the_rsu_answers_a_query_once_by_querier_seq_and_t1():
    answers = TimeAnswers(capacity=3)
    query = TimeRequest(obu_id="ego", seq=1, t1_ns=T0)
    assert answers.first(query) and not answers.first(query)  # a duplicate or a relayed copy
    # a query forged ahead with the victim's id and next seq does not use up the genuine one's answer
    assert answers.first(TimeRequest(obu_id="ego", seq=2, t1_ns=T0 + 1))
    assert answers.first(TimeRequest(obu_id="ego", seq=2, t1_ns=T0 + 100 * MS))
    assert answers.first(TimeRequest(obu_id="car-2", seq=1, t1_ns=T0))  # another querier
    assert answers.first(query)  # forgotten (capacity 3): answered again, the OBU keeps the first reply


def two_genuine_replies(request: TimeRequest):
    """What a relay gets the RSU to send: its answer to the query and to a copy forwarded 100 ms later."""
    first = answer_time_request(request, RSU, request.t1_ns + 5 * MS + THETA, request.t1_ns + 6 * MS + THETA)
    later = answer_time_request(request, RSU, request.t1_ns + 105 * MS + THETA, request.t1_ns + 106 * MS + THETA)
    return first, later


@pytest.mark.parametrize("order", ["first, later", "later, first"])
def test_the_first_verified_reply_counts_and_a_later_one_is_ignored_not_voided(order):
    requests = TimeRequests("ego", hold_ns=150 * MS)
    req = requests.make(T0)
    first, later = two_genuine_replies(req)
    a, b = (first, later) if order == "first, later" else (later, first)
    assert requests.match(a, T0 + 10 * MS, verified=True) is None
    assert requests.match(b, T0 + 111 * MS, verified=True) == "time_reply_later"
    assert requests.match(b, T0 + 112 * MS, verified=True) == "time_reply_later"
    [(rsu_id, sample)] = requests.ripe(T0 + 1_000 * MS)
    assert rsu_id == RSU and sample.t2_ns == a.t2_ns
    assert requests.ripe(T0 + 2_000 * MS) == []  # once


def test_unverified_replies_still_void_each_other_and_a_verified_one_replaces_them():
    requests = TimeRequests("ego", hold_ns=150 * MS)
    first, later = two_genuine_replies(requests.make(T0))
    assert requests.match(first, T0 + 10 * MS) is None
    assert requests.match(later, T0 + 111 * MS) == "time_reply_conflict"
    assert requests.ripe(T0 + 1_000 * MS) == []
    req = requests.make(T0 + 1_000 * MS)
    first, later = two_genuine_replies(req)
    assert requests.match(later, T0 + 1_010 * MS) is None  # unsigned, say a forger's
    assert requests.match(first, T0 + 1_020 * MS, verified=True) is None  # the RSU's own: it takes the place
    [(_, sample)] = requests.ripe(T0 + 2_000 * MS)
    assert sample.t2_ns == first.t2_ns


def test_a_relay_doubling_every_genuine_reply_does_not_stop_a_strict_obus_clock():
    """Through the OBU's inbox with a site PKI (strict): every query answered twice by the RSU (its
    reply to the query and to a relayed copy), both signed; the clock forms from the first of each."""
    trust, ids = memory_site(T0 - 86_400 * 10**9, [RSU], [])
    signer = Signer(ids[RSU])
    p = ObuPipeline(ObuPipelineConfig(fusion="iou-merge"))
    inbox = Inbox(p, InboundSecurity(make_verifier(trust, "strict", 5.0), p.clock_offset, p.reject))
    key = keys.rsu_time(RSU)
    for k in range(40):
        t1 = T0 + k * 100 * MS
        first, later = two_genuine_replies(p.make_time_request(t1))
        for reply, t4 in ((first, t1 + 11 * MS), (later, t1 + 111 * MS)):
            assert inbox.take("time", key, signer.sign(encode(reply), reply.t3_ns, key), t4) is Outcome.READ
    est = p.clock_offset(RSU, T0 + 4_000 * MS)
    assert est is not None and est.samples >= 35 and abs(est.offset_ns - THETA) < 2 * MS
    assert p.rejected["time_reply_later"] == 40 and "time_reply_conflict" not in p.rejected
