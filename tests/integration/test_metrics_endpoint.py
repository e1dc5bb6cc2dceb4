"""A real ``v2i obu`` process serves ``/metrics`` (``--metrics-port``): its cycle counter grows while
it runs; a second service asking for the same port stops at start-up with exit status 2."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request

import pytest
from prometheus_client.parser import text_string_to_metric_families

from v2i.orchestration.children import READY_TIMEOUT_S, START_LEAD_S, Child, start_all, wait_ready
from v2i.runtime.transport import free_tcp_endpoint

pytestmark = [pytest.mark.integration, pytest.mark.timeout(2 * READY_TIMEOUT_S + 30)]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cycles_total(url: str) -> float | None:
    """``v2i_obu_cycles_total`` of one scrape; None while the endpoint is not up or has no metrics yet."""
    try:
        text = urllib.request.urlopen(url, timeout=2).read().decode()
    except (urllib.error.URLError, ConnectionError):
        return None
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            if sample.name == "v2i_obu_cycles_total":
                return sample.value
    return None


def wait_for_cycles(url: str, proc: subprocess.Popen, at_least: float, timeout_s: float) -> float:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"the OBU exited early with {proc.returncode}"
        value = cycles_total(url)
        if value is not None and value >= at_least:
            return value
        time.sleep(0.1)  # a poll period, not a wait for an event
    pytest.fail(f"v2i_obu_cycles_total did not reach {at_least} within {timeout_s} s at {url}")


def test_a_running_obu_serves_growing_cycle_counts_and_a_taken_port_is_a_start_up_error():
    port = free_port()
    url = f"http://127.0.0.1:{port}/metrics"
    argv = [sys.executable, "-m", "v2i", "obu", "--duration", "60", "--metrics-port", str(port)]
    obu = Child("obu", [*argv, "--listen", free_tcp_endpoint(), "--await-start"])
    try:
        wait_ready([obu])  # its /metrics is served from before the ready line
        start_all([obu])
        # the first cycle at time zero, 10 Hz: the counter grows within a second; 10 s for a busy machine
        first = wait_for_cycles(url, obu.proc, 1, START_LEAD_S + 10.0)
        wait_for_cycles(url, obu.proc, first + 3, 10.0)  # read at scrape time: it follows the running node
        # a second OBU (not awaiting a start: the port is checked at start-up), up to its start-up bound
        second = subprocess.run([*argv, "--listen", free_tcp_endpoint()], capture_output=True, text=True,
                                timeout=READY_TIMEOUT_S)
        assert second.returncode == 2
        assert f"--metrics-port {port}: cannot listen on 127.0.0.1:{port}" in second.stderr
    finally:
        obu.stop(timeout_s=10.0)
    assert obu.proc.returncode == 0
