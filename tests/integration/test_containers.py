"""RSU, link emulator and OBU in podman containers: ``deploy/compose.yaml`` under podman-compose.

The compose file puts the RSU on ``rsu-net`` only, the OBU on ``obu-net`` only and the link
emulator on both (internal networks, no route out); the ``watch`` service on ``obu-net`` counts
the OBU's fused lists that hold RSU objects, which only the emulator can have carried across.
The project name is unique to this run (containers ``NAME_SERVICE_1``, networks ``NAME_rsu-net``,
``NAME_obu-net``), and everything it created is removed afterwards, also on failure.

Runs only where it can: root, podman, podman-compose and the image ``$V2I_IMAGE`` (default
``v2i:latest``, built by ``deploy/podman/build.sh``). CI does not build images: without the image
the test is skipped, unless ``V2I_PODMAN_BUILD=1`` asks this test to run the build first.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.timeout(600)]  # a requested build takes minutes

REPO = Path(__file__).resolve().parents[2]
COMPOSE_FILE = REPO / "deploy" / "compose.yaml"
BUILD_SCRIPT = REPO / "deploy" / "podman" / "build.sh"
IMAGE = os.environ.get("V2I_IMAGE", "v2i:latest")
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
    """Remove this project's containers and networks (and nothing else); what is still left."""
    label = f"label=io.podman.compose.project={project.name}"
    ids = _podman("ps", "--all", "--quiet", "--filter", label).stdout.split()
    if ids:
        _podman("rm", "--force", "--time", "2", *ids)
    for net in ("rsu-net", "obu-net"):
        if _podman("network", "exists", project.network(net)).returncode == 0:
            _podman("network", "rm", project.network(net))
    left = _podman("ps", "--all", "--quiet", "--filter", label).stdout.split()
    return left + [n for n in ("rsu-net", "obu-net") if _podman("network", "exists", project.network(n)).returncode == 0]


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


def _compose(project: Project, *args: str) -> subprocess.CompletedProcess[str]:
    """``podman-compose -p NAME -f deploy/compose.yaml ARGS`` with podman's flags for this machine."""
    command = ["podman-compose", "--podman-args", " ".join(PODMAN[1:]), "-p", project.name,
               "-f", str(COMPOSE_FILE), *args]
    return subprocess.run(command, capture_output=True, text=True, env=project.env, timeout=120, check=False)


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
    up = _compose(project, "up", "-d", *SERVICES)
    assert up.returncode == 0, up.stdout + up.stderr
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
    stop = _podman("stop", "--time", str(STOP_TIMEOUT_S), rsu, obu, link, timeout_s=3 * STOP_TIMEOUT_S + 30)
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
    assert [_exit_code(c) for c in (rsu, obu, link)] == [0, 0, 0], logs


def _exit_code(container: str) -> int:
    return int(_podman("inspect", "--format", "{{.State.ExitCode}}", container).stdout.strip())
