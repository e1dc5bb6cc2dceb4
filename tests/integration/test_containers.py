"""RSU, link emulator and OBU in podman containers: ``deploy/compose.yaml`` under podman-compose.

The compose file puts the RSU on ``rsu-net`` only, the OBU on ``obu-net`` only and the link
emulator on both (internal networks, no route out); the ``watch`` service on ``obu-net`` counts
the OBU's fused lists that hold RSU objects, which only the emulator can have carried across.
The site is secured (issue 14): the one-shot ``pki`` service writes the signing PKI and the TLS
material into the project's volume, every session is mutual TLS with the role's access control
(``deploy/zenoh/*.json5``), the RSU signs and the OBU verifies strictly; the test checks that a
plain ``tcp/`` session and a site certificate of the wrong name get none of the OBU's output while a
monitor's does, and that unsigned lists sent with a certificate the ACL admits are all dropped as
``security_unsigned`` while the genuine RSU's signed lists are accepted.
With the ``prometheus`` service (Debian's prometheus, ``build.sh --prometheus``), Prometheus
scrapes the three services' /metrics (plain HTTP) across both networks.
The project name is unique to this run (containers ``NAME_SERVICE_1``, networks ``NAME_rsu-net``,
``NAME_obu-net``), and everything it created is removed afterwards, also on failure.

Runs only where it can: root, podman, podman-compose and the image ``$V2I_IMAGE`` (default
``v2i:latest``, built by ``deploy/podman/build.sh``; the Prometheus test also
``$V2I_PROMETHEUS_IMAGE``, default ``v2i-prometheus:latest``). CI does not build images: without the image
the test is skipped, unless ``V2I_PODMAN_BUILD=1`` asks this test to run the build first.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import subprocess
import time
import urllib.parse
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.timeout(600)]  # a requested build takes minutes

REPO = Path(__file__).resolve().parents[2]
COMPOSE_FILE = REPO / "deploy" / "compose.yaml"
BUILD_SCRIPT = REPO / "deploy" / "podman" / "build.sh"
IMAGE = os.environ.get("V2I_IMAGE", "v2i:latest")
PROMETHEUS_IMAGE = os.environ.get("V2I_PROMETHEUS_IMAGE", "v2i-prometheus:latest")
PROMETHEUS_CONFIG = REPO / "deploy" / "prometheus" / "prometheus.yml"
# The compose file's /metrics endpoints, as Prometheus's `instance` labels.
METRICS_TARGETS = {"rsu:9101", "link:9102", "obu:9103"}
# podman as it runs on these machines (deploy/README.md): runc and cgroupfs (crun fails here).
PODMAN = ("podman", "--runtime", "runc", "--cgroup-manager", "cgroupfs")
SERVICES = ("rsu", "obu", "link", "watch")
# podman-compose 1.0.3 starts the containers one by one (pausing 1 s after each), then three
# interpreters import numpy, scipy, OpenCV... on two shared cores before the scenario starts.
STARTUP_S = 15.0
RUN_S = 30  # scenario seconds RSU and OBU would run; they are stopped once the watcher is done
MIN_RSU_LISTS = 20
WATCH_TIMEOUT_S = 45.0  # the watcher's own limit, from its start
STOP_TIMEOUT_S = 10  # SIGTERM (forwarded by the init process), then SIGKILL
SCRAPE_WAIT_S = 40.0  # after the scenario start: a few scrape intervals


def _podman(*args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*PODMAN, *args], capture_output=True, text=True, timeout=timeout_s, check=False)


def _skip_reason() -> str | None:
    """Why the container test cannot run here, or None."""
    if shutil.which("podman") is None:
        return "podman is not installed"
    if shutil.which("podman-compose") is None:
        return "podman-compose is not installed"
    if os.geteuid() != 0:
        return "needs root (rootful podman: bridge networks between containers)"
    return None


@pytest.fixture(scope="module")
def image() -> str:
    """The image tag, built first when ``V2I_PODMAN_BUILD=1`` asks for it; skip when absent."""
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    if os.environ.get("V2I_PODMAN_BUILD") == "1":
        subprocess.run([str(BUILD_SCRIPT)], check=True, env={**os.environ, "V2I_IMAGE": IMAGE}, timeout=1800)
    if _podman("image", "exists", IMAGE).returncode != 0:
        pytest.skip(f"image {IMAGE} not built (deploy/podman/build.sh, or V2I_PODMAN_BUILD=1)")
    return IMAGE


@dataclass(frozen=True)
class Project:
    """One compose project of this run: its name and the environment the compose file reads."""

    name: str
    env: dict[str, str]

    def container(self, service: str) -> str:
        return f"{self.name}_{service}_1"

    def network(self, net: str) -> str:
        return f"{self.name}_{net}"


def _remove_project(project: Project) -> list[str]:
    """Remove this project's containers, networks and volumes (nothing else); what is still left."""
    label = f"label=io.podman.compose.project={project.name}"
    ids = _podman("ps", "--all", "--quiet", "--filter", label).stdout.split()
    if ids:
        _podman("rm", "--force", "--time", "2", *ids)
    nets = [project.network(n) for n in ("rsu-net", "obu-net")]
    for net in nets:
        if _podman("network", "exists", net).returncode == 0:
            _podman("network", "rm", net)
    volumes = _podman("volume", "ls", "--quiet", "--filter", label).stdout.split()
    if volumes:
        _podman("volume", "rm", *volumes)
    left = _podman("ps", "--all", "--quiet", "--filter", label).stdout.split()
    left += _podman("volume", "ls", "--quiet", "--filter", label).stdout.split()
    return left + [n for n in nets if _podman("network", "exists", n).returncode == 0]


@pytest.fixture
def project(image: str) -> Iterator[Project]:
    name = f"v2it{secrets.token_hex(4)}"
    start_at_ns = time.time_ns() + int(STARTUP_S * 1e9)
    env = {**os.environ, "V2I_IMAGE": image, "V2I_START_AT_NS": str(start_at_ns), "V2I_DURATION_S": str(RUN_S),
           "V2I_WATCH_MIN_RSU_LISTS": str(MIN_RSU_LISTS), "V2I_WATCH_TIMEOUT_S": str(WATCH_TIMEOUT_S)}
    created = Project(name, env)
    try:
        yield created
    finally:
        left = _remove_project(created)
        assert not left, f"not removed: {left}"


def _up(project: Project, *services: str) -> None:
    """``podman-compose -p NAME -f deploy/compose.yaml up -d SERVICES`` with podman's flags for this
    machine; AssertionError unless every service's container was made (1.0.3 exits 0 regardless)."""
    command = ["podman-compose", "--podman-args", " ".join(PODMAN[1:]), "-p", project.name,
               "-f", str(COMPOSE_FILE), "up", "-d", *services]
    up = subprocess.run(command, capture_output=True, text=True, env=project.env, timeout=120, check=False)
    label = f"label=io.podman.compose.project={project.name}"
    made = set(_podman("ps", "--all", "--format", "{{.Names}}", "--filter", label).stdout.split())
    assert up.returncode == 0 and made == {project.container(s) for s in services}, up.stdout + up.stderr


def _networks(container: str) -> set[str]:
    out = _podman("inspect", "--format", "{{json .NetworkSettings.Networks}}", container)
    assert out.returncode == 0, out.stderr
    return set(json.loads(out.stdout))


def _address(container: str, network: str) -> str:
    out = _podman("inspect", "--format", "{{json .NetworkSettings.Networks}}", container)
    return json.loads(out.stdout)[network]["IPAddress"]


# Run inside the RSU container: exit 0 if a TCP connection to HOST:PORT opens, 1 (and the reason)
# if not. Both by address and by name: neither may lead to the OBU.
_PROBE = """
import socket, sys
try:
    socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=3).close()
except OSError as exc:
    print(type(exc).__name__, exc)
    sys.exit(1)
print("connected")
"""


def _probe(container: str, host: str, port: int) -> subprocess.CompletedProcess[str]:
    return _podman("exec", container, "python", "-c", _PROBE, host, str(port))


# Run inside the emulator's container (on obu-net, the site PKI at /pki): what reaches whom on the
# secured OBU. Subscribes to the OBU's fused output for WINDOW_S seconds each as (1) a plain tcp/
# session, (2) a TLS session with a valid site certificate of a name the OBU's ACL does not admit
# ("operator"), (3) a monitor (the positive control: the same subscription, admitted); then (4)
# holding the emulator's own certificate (which the ACL lets publish RSU data into the OBU) puts
# UNSIGNED bytes on the RSU's object key, which the strict OBU must drop as security_unsigned; and
# reads the OBU's /metrics until that count is reached (deadline). Prints one JSON object.
_SECURITY_PROBE = """
import json, os, sys, time, urllib.request
from prometheus_client.parser import text_string_to_metric_families
from schemas.keys import obu_objects, rsu_objects
from v2i.runtime.transport import open_session
window_s, unsigned_puts = float(sys.argv[1]), int(sys.argv[2])
wrong_name = {"transport": {"link": {"tls": {"root_ca_certificate": "/pki/tls/tls-ca.pem",
    "connect_certificate": "/pki/tls/operator.pem", "connect_private_key": "/pki/tls/operator.key",
    "enable_mtls": True, "verify_name_on_connect": True}}}}
with open("/tmp/wrong-name.json5", "w") as f:
    json.dump(wrong_name, f)
def fused_received(config, endpoint):
    os.environ.pop("V2I_ZENOH_CONFIG", None)
    if config:
        os.environ["V2I_ZENOH_CONFIG"] = config
    received = []
    session = open_session(connect=[endpoint])
    subscriber = session.declare_subscriber(obu_objects("ego"), lambda sample: received.append(1))
    time.sleep(window_s)  # the observation window: counting what arrives in it
    subscriber.undeclare()
    session.close()
    return len(received)
def obu_metrics():
    text = urllib.request.urlopen("http://obu:9103/metrics", timeout=3).read().decode()
    values = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            key = s.name + ("[" + s.labels["reason"] + "]" if "reason" in s.labels else "")
            values[key] = values.get(key, 0.0) + s.value
    return values
result = {"tcp": fused_received(None, "tcp/obu:7448"),
          "wrong_name": fused_received("/tmp/wrong-name.json5", "tls/obu:7448"),
          "monitor": fused_received("/etc/v2i/zenoh/monitor.json5", "tls/obu:7448")}
os.environ["V2I_ZENOH_CONFIG"] = "/etc/v2i/zenoh/link.json5"
session = open_session(connect=["tls/obu:7448"])
time.sleep(1.0)  # the TLS handshake and the OBU's subscription reaching this session
for _ in range(unsigned_puts):
    session.put(rsu_objects("rsu1"), b"ghost list, not signed")
    time.sleep(0.05)
deadline = time.monotonic() + 10.0
while (metrics := obu_metrics()).get("v2i_obu_rejected_total[security_unsigned]", 0) < unsigned_puts \
        and time.monotonic() < deadline:
    time.sleep(0.2)  # polling the OBU's metrics until the deadline
session.close()
result["obu_rejected"] = {k.split("[")[1][:-1]: v for k, v in metrics.items() if k.startswith("v2i_obu_rejected_total[")}
result["obu_rsu_lists_accepted"] = metrics.get("v2i_obu_rsu_lists_accepted_total", 0.0)
print(json.dumps(result))
"""
PROBE_WINDOW_S = 3.0
UNSIGNED_PUTS = 20


def _security_probe(container: str) -> dict:
    out = _podman("exec", container, "python", "-c", _SECURITY_PROBE, str(PROBE_WINDOW_S), str(UNSIGNED_PUTS),
                  timeout_s=60.0)
    assert out.returncode == 0, out.stdout + out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def _wait_exit(container: str, deadline: float) -> int:
    """The container's exit status once it exits; AssertionError at the deadline (monotonic s)."""
    try:
        out = _podman("wait", container, timeout_s=max(deadline - time.monotonic(), 0.1))
    except subprocess.TimeoutExpired:
        raise AssertionError(f"{container} still running at the deadline:\n{_logs(container)}") from None
    assert out.returncode == 0, out.stderr
    return int(out.stdout.strip())


def _logs(container: str) -> str:
    out = _podman("logs", container)
    return out.stdout + out.stderr


def _events(log: str) -> list[dict]:
    return [json.loads(line) for line in log.splitlines() if line.startswith("{")]


def test_fused_output_carries_rsu_objects_across_the_two_networks(project: Project) -> None:
    _up(project, "pki", *SERVICES)
    rsu, obu, link, watch = (project.container(s) for s in SERVICES)
    rsu_net, obu_net = project.network("rsu-net"), project.network("obu-net")

    assert _networks(rsu) == {rsu_net}
    assert _networks(obu) == {obu_net}
    assert _networks(link) == {rsu_net, obu_net}
    assert _networks(watch) == {obu_net}
    # The RSU has no path to the OBU but through the emulator: not by address, not by name.
    for host in (_address(obu, obu_net), "obu"):
        probe = _probe(rsu, host, 7448)
        print(f"RSU -> OBU at {host}: {probe.stdout.strip()}")
        assert probe.returncode == 1, f"RSU reached the OBU at {host}: {probe.stdout}{probe.stderr}"
    # The same probe does find a path where there is one: the emulator reaches both services.
    for host, port in (("rsu", 7447), ("obu", 7448)):
        probe = _probe(link, host, port)
        assert probe.returncode == 0, f"the emulator did not reach {host}:{port}: {probe.stdout}{probe.stderr}"

    status = _wait_exit(watch, time.monotonic() + STARTUP_S + WATCH_TIMEOUT_S + 15.0)
    # TLS, ACL and signatures in force while the services still run (RUN_S of scenario time).
    security = _security_probe(link)
    print("security probe:", security)
    # The emulator first, as `podman-compose down` does (reverse start order): once its peers are
    # gone it retries them by name, and each lookup blocks Zenoh's runtime for the resolver's 5 s
    # timeout (aardvark-dns forwards unknown names upstream, unreachable from internal networks),
    # which can hold its shutdown past the grace period.
    for containers in ((link,), (rsu, obu)):
        stop = _podman("stop", "--time", str(STOP_TIMEOUT_S), *containers, timeout_s=2 * STOP_TIMEOUT_S + 30)
        assert stop.returncode == 0, stop.stderr
    logs = {c: _logs(c) for c in (rsu, obu, link, watch)}
    for container, log in logs.items():  # shown with -s / -rP: the end of each service's log
        print(f"--- {container}:", *log.strip().splitlines()[-2:], sep="\n  ")

    events = _events(logs[watch])
    fused_with_rsu = [e for e in events if e["event"] == "fused" and e["rsu_objects"] > 0]
    done = [e for e in events if e["event"] == "done"]
    assert status == 0, logs
    assert done and done[0]["lists_with_rsu_objects"] >= MIN_RSU_LISTS, logs[watch]
    assert len(fused_with_rsu) == done[0]["lists_with_rsu_objects"]
    # Each service stopped cleanly on SIGTERM (its summary line), the RSU after publishing.
    assert "[rsu] stopped:" in logs[rsu] and "[obu] stopped:" in logs[obu], logs
    assert [_exit_code(c) for c in (project.container("pki"), rsu, obu, link)] == [0, 0, 0, 0], logs
    # A plain tcp/ session and a site certificate of the wrong name get none of the OBU's output, a
    # monitor's does; the unsigned lists an admitted certificate sent were all dropped, and
    # nothing else was: the genuine RSU's signed lists were accepted.
    assert security["tcp"] == 0 and security["wrong_name"] == 0 and security["monitor"] > 0, security
    assert security["obu_rejected"] == {"security_unsigned": UNSIGNED_PUTS}, security
    assert security["obu_rsu_lists_accepted"] >= MIN_RSU_LISTS, security


def _exit_code(container: str) -> int:
    return int(_podman("inspect", "--format", "{{.State.ExitCode}}", container).stdout.strip())


def _query(address: str, promql: str) -> list[dict]:
    """The result vector of an instant PromQL query on the Prometheus at ``address`` (port 9090)."""
    url = f"http://{address}:9090/api/v1/query?" + urllib.parse.urlencode({"query": promql})
    with urllib.request.urlopen(url, timeout=3) as response:
        return json.load(response)["data"]["result"]


def _scraped(address: str) -> dict[str, float] | None:
    """What the test waits for, once Prometheus has it: targets up, RSU lists published by the RSU,
    relayed by the emulator and accepted by the OBU; else None."""
    try:
        up = {r["metric"]["instance"] for r in _query(address, "up == 1")}
        totals = {name: sum(float(r["value"][1]) for r in _query(address, name)) for name in
                  ("v2i_rsu_published_total", "v2i_link_stage_seconds_count", "v2i_obu_rsu_lists_accepted_total")}
    except OSError:  # not listening yet
        return None
    return totals if METRICS_TARGETS <= up and all(totals.values()) else None


def test_prometheus_scrapes_the_three_services(project: Project) -> None:
    if _podman("image", "exists", PROMETHEUS_IMAGE).returncode != 0:
        pytest.skip(f"image {PROMETHEUS_IMAGE} not built (deploy/podman/build.sh --prometheus)")
    if not PROMETHEUS_CONFIG.is_file():
        pytest.skip(f"{PROMETHEUS_CONFIG} missing")
    _up(project, "pki", "rsu", "obu", "link", "prometheus")
    prometheus, rsu_net = project.container("prometheus"), project.network("rsu-net")
    assert _networks(prometheus) == {rsu_net, project.network("obu-net")}
    address = _address(prometheus, rsu_net)
    deadline = time.monotonic() + STARTUP_S + SCRAPE_WAIT_S
    while (totals := _scraped(address)) is None and time.monotonic() < deadline:
        time.sleep(1.0)  # polling Prometheus's API until the deadline
    with urllib.request.urlopen(f"http://{address}:9090/api/v1/targets", timeout=3) as response:
        targets = {t["labels"]["instance"]: (t["health"], t["lastError"]) for t in json.load(response)["data"]["activeTargets"]}
    print("targets:", targets, "totals:", totals)
    assert totals is not None, targets
