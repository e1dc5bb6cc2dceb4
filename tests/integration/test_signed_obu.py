"""A signing RSU and a strict OBU on real Zenoh: genuine lists fuse, injected ones are dropped and counted."""

from __future__ import annotations

import queue
import time

import pytest

from v2i.orchestration.children import READY_TIMEOUT_S
from obu_service.config import ObuConfig
from rsu_service.config import RsuConfig
from schemas import keys
from schemas.codec import decode, encode
from schemas.limits import SOURCE_RSU
from schemas.messages import FusedObjectList, ObjectList, ObjectListHeader, ObuMetrics, TimeReply, TimeRequest
from v2i.runtime.transport import free_tcp_endpoint
from v2i.security.envelope import Signer
from v2i.security.pki import load_signer
from v2i.security.site import write_site
from v2i.services import obu_node, rsu_node

from test_obu_node import RUN_S, probe_session, running, wait_for  # tests/integration is on sys.path (rootdir-less)

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60 + READY_TIMEOUT_S)]
INJECTED = 8  # of each kind


def _forge_reply(query) -> int:
    """Answer an OBU time query as rsu1, unsigned, 400 ms off (a clock-shifting attacker)."""
    request = decode(query.payload.to_bytes(), TimeRequest)
    t_ns = time.time_ns() + 650_000_000  # the RSU's clock runs 250 ms ahead: this says 650
    query.reply(keys.rsu_time("rsu1"), encode(TimeReply(rsu_id="rsu1", seq=request.seq, t1_ns=request.t1_ns,
                                                        t2_ns=t_ns, t3_ns=t_ns)))
    return request.seq


def _has_rsu_objects(out: FusedObjectList) -> bool:
    return bool(len(out.objects)) and bool((out.objects.column("sources").astype(int) & SOURCE_RSU).any())


def test_strict_obu_fuses_the_signing_rsu_and_counts_every_injection(tmp_path):
    pki = write_site(tmp_path, time.time_ns() - 10**9, ["rsu1", "rsu2"], ["ego"])
    rsu_ep, obu_ep = free_tcp_endpoint(), free_tcp_endpoint()
    rsu = rsu_node(RsuConfig(listen=[rsu_ep], await_start=True, duration_s=RUN_S, clock_offset_ms=250.0,
                             pki_dir=str(pki)))
    obu = obu_node(ObuConfig(listen=[obu_ep], connect=[rsu_ep], await_start=True, duration_s=RUN_S, pki_dir=str(pki)))
    assert obu.config.security_policy == "strict"
    outputs, metrics, forged_replies = queue.Queue(), queue.Queue(), []
    with running(rsu, obu), probe_session(obu_ep) as (probe, entities):
        entities += [
            probe.declare_queryable(keys.rsu_time("rsu1"), lambda q: forged_replies.append(_forge_reply(q))),
            probe.declare_subscriber(keys.obu_objects("ego"), lambda s: outputs.put(decode(s.payload.to_bytes(), FusedObjectList))),
            probe.declare_subscriber(keys.obu_metrics("ego"), lambda s: metrics.put(decode(s.payload.to_bytes(), ObuMetrics)))]
        wait_for(outputs, _has_rsu_objects, 15.0)
        ghost = encode(ObjectList(header=ObjectListHeader(rsu_id="rsu1", seq=10_000, capture_time_ns=time.time_ns(),
                                                          publish_time_ns=time.time_ns())))
        key = keys.rsu_objects("rsu1")
        intruder = Signer(load_signer(pki, "rsu2"))  # a genuine certificate of another RSU: key substitution
        for k in range(INJECTED):  # within the intake's burst on one key (25)
            probe.put(key, ghost)  # unsigned
            probe.put(key, intruder.sign(ghost, time.time_ns() + k, key))
        m = wait_for(metrics, lambda m: m.rejected.get("security_unsigned", 0) >= INJECTED + len(forged_replies) > INJECTED
                     and m.rejected.get("security_wrong_key", 0) >= INJECTED, 10.0)
        assert not any(reason.startswith("security_") and reason not in ("security_unsigned", "security_wrong_key")
                       for reason in m.rejected), m.rejected
        rsu1 = next(r for r in m.rsus if r.rsu_id == "rsu1")
        assert abs(rsu1.clock_offset_ns - 250_000_000) < 5_000_000  # the signed replies synchronise, the forged do not
        assert m.output_deadline_misses == 0
        wait_for(outputs, _has_rsu_objects, 5.0)  # and the genuine RSU keeps fusing
        assert "sign" in rsu.last_metrics.latency_ms and "verify" in m.latency_ms  # both sides' stages
