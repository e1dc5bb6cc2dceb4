"""A revocation issued while the OBU runs: a strict OBU fuses a signing RSU's lists, ``v2i pki revoke``
revokes the RSU's certificate, and from then on the OBU refuses its messages as ``security_revoked``."""

from __future__ import annotations

import queue
import subprocess
import sys
import time

import pytest

from v2i.orchestration.children import READY_TIMEOUT_S
from obu_service.config import ObuConfig
from rsu_service.config import RsuConfig
from schemas import keys
from schemas.codec import decode
from schemas.messages import ObuMetrics
from v2i.runtime.transport import free_tcp_endpoint
from v2i.security.pki import CRL_FILE
from v2i.security.site import write_site
from v2i.services import obu_node, rsu_node

from test_obu_node import probe_session, running, wait_for  # tests/integration is on sys.path (rootdir-less import)

READY_S = 30.0  # from time zero (the nodes are ready) to the first accepted RSU list: ~1 s, generous for a busy machine
REVOKED_S = 30.0  # to the first refusal after the revocation: the OBU looks once a second, after a cycle's output
# After the first refusal, lists keep coming at 10 Hz (and time replies): at least this many more refused, none
# accepted, within REVOKED_S; 5 is half a second of lists, a margin for a busy machine's late cycles.
MORE_REFUSED = 5
REVOKE_S = 60.0  # v2i pki revoke, a process
pytestmark = [pytest.mark.integration, pytest.mark.timeout(READY_TIMEOUT_S + READY_S + REVOKE_S + 2 * REVOKED_S)]


def _rsu1(m: ObuMetrics):
    return next((r for r in m.rsus if r.rsu_id == "rsu1"), None)


def _accepted(m: ObuMetrics) -> int:
    row = _rsu1(m)
    return 0 if row is None else row.messages_accepted


def test_a_revocation_written_while_the_obu_runs_refuses_the_rsu_from_then_on(tmp_path, capsys):
    pki = write_site(tmp_path / "pki", time.time_ns() - 10**9, ["rsu1"], ["ego"])
    rsu_ep, obu_ep = free_tcp_endpoint(), free_tcp_endpoint()
    rsu = rsu_node(RsuConfig(listen=[rsu_ep], await_start=True, duration_s=180.0, pki_dir=str(pki)))
    obu = obu_node(ObuConfig(listen=[obu_ep], connect=[rsu_ep], await_start=True, duration_s=180.0, pki_dir=str(pki)))
    assert obu.config.security_policy == "strict"
    metrics: queue.Queue = queue.Queue()
    with running(rsu, obu), probe_session(obu_ep) as (probe, entities):
        entities.append(probe.declare_subscriber(keys.obu_metrics("ego"),
                                                 lambda s: metrics.put(decode(s.payload.to_bytes(), ObuMetrics))))
        before = wait_for(metrics, lambda m: _accepted(m) > 0, READY_S)
        assert not any(k.startswith("security_") for k in before.rejected), before.rejected
        revoke = subprocess.run([sys.executable, "-m", "v2i", "pki", "revoke", str(pki), "rsu1"],
                                capture_output=True, text=True, timeout=REVOKE_S)
        assert revoke.returncode == 0 and "rsu1: revoked" in revoke.stdout, revoke.stderr
        first = wait_for(metrics, lambda m: m.rejected.get("security_revoked", 0) > 0, REVOKED_S)
        refused = first.rejected["security_revoked"]
        later = wait_for(metrics, lambda m: m.rejected.get("security_revoked", 0) >= refused + MORE_REFUSED, REVOKED_S)
        assert _accepted(later) == _accepted(first)  # nothing of rsu1's accepted after the first refusal
        assert not any(k.startswith("security_") and k != "security_revoked" for k in later.rejected), later.rejected
    logged = [line for line in capsys.readouterr().err.splitlines() if "reloaded" in line]
    assert len(logged) == 1 and logged[0].startswith("[obu") and logged[0].endswith(
        f"] reloaded {pki / CRL_FILE}: 1 certificate(s) revoked"), logged
