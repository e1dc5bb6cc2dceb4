"""RSU, link emulator and OBU in network namespaces over ``tls/`` endpoints, mutual TLS and the
shipped access-control configs (``deploy/zenoh/*.json5``), against an intruder on the vehicle host.

Topology and helpers are ``test_netns``'s (imported, not copied):

    rsu 10.10.1.1 <-veth-> 10.10.1.2 link 10.10.2.1 <-veth-> 10.10.2.2 obu (+ intruder, judge)

The link emulator also listens for link control on ``tls/10.10.2.1:7450``. Certificates
(``v2i.security.tls.issue_tls``): ``rsu@10.10.1.1``, ``obu@10.10.2.2``, ``link@10.10.2.1``,
``operator``, ``monitor`` and ``vehicle-2``, a valid certificate of the site with the wrong name.

This file is also the program run inside the OBU namespace (``python test_netns_tls.py probe``):
a judge (CN ``monitor``) watches the OBU's fused output and the emulator's stats while

1. a process without a client certificate tries the OBU and the control endpoint: it must not
   connect at all;
2. ``vehicle-2`` connects to both (checked) and, for a few seconds, puts ghost pedestrians 8 m
   ahead of the ego on ``v2x/rsu/{rsu_id}/objects`` (``v2i.adversary.attack_messages``) and link
   outages on ``v2x/link/{id}/control``: no ghost may show in the fused output
   (``v2i.adversary.attack_ghosts.GhostWatch``) and the emulator's ``control.applied`` stays 0;
3. positive controls, so that 2. cannot pass vacuously: the same ghosts put with the ``rsu``
   certificate (a name the OBU's ACL admits) do show, and one control put with the ``operator``
   certificate is applied. The OBU runs without ``--pki`` (security off) and the emulator with
   ``--insecure-control`` where it has it: the ACL is the only guard being tested.

Needs root and iproute2; skipped, with the reason, elsewhere.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import queue
import secrets
import sys
import time
from pathlib import Path

import pytest
import test_netns as netns  # tests/integration is on sys.path (pytest's rootdir-less import; the script's folder)

from v2i.orchestration.children import READY_TIMEOUT_S

# the probe process's own waits: up to 25 s for the genuine traffic, then two intruder phases and the positive
# controls (each up to 5 s to connect, 3 s of ghosts, 1.5-5 s for what is in flight): ~70 s at most
PROBE_S = 90.0
RUN_S = READY_TIMEOUT_S + PROBE_S  # the services' run from time zero; stopped when the probe is done
pytestmark = [pytest.mark.integration, pytest.mark.timeout(2 * READY_TIMEOUT_S + PROBE_S + 30)]

SRC = Path(__file__).resolve().parents[2] / "src"
DEPLOY = Path(__file__).resolve().parents[2] / "deploy" / "zenoh"
CONTROL_PORT = 7450
VEHICLE_ID, LINK_ID = "ego", "link1"  # the scenario's vehicle, the emulator's default id
GHOST_SECONDS, GHOST_RATE_HZ = 3.0, 10.0
FAKE_RSU = "rsu-x"  # an RSU id of the intruder's own: any list of it the OBU accepts shows in its metrics
CONNECT_TIMEOUT_S = 5.0


# ----------------------------------------------------------------------------- the test
def _names() -> list[str]:
    return [f"rsu@{netns.RSU_ADDR}", f"obu@{netns.OBU_ADDR}", f"link@{netns.LINK_OBU_ADDR}", "operator", "monitor",
            "vehicle-2"]


def _control_flags() -> list[str]:
    """``--insecure-control`` where the emulator authenticates control by default (issue 14), so
    that the ACL is the only guard of the control endpoint; nothing where it does not."""
    return ["--insecure-control"] if importlib.util.find_spec("link_emulator.control_auth") else []


def _start(topo, tls_dir: Path, link_config: Path, children: dict) -> dict[str, str]:
    """RSU, OBU and emulator with their shipped configs; returns the endpoints."""
    from v2i.orchestration.children import Child, start_all, wait_ready

    eps = {"rsu": f"tls/{netns.RSU_ADDR}:{netns.RSU_PORT}", "obu": f"tls/{netns.OBU_ADDR}:{netns.OBU_PORT}",
           "control": f"tls/{netns.LINK_OBU_ADDR}:{CONTROL_PORT}"}
    env = ("env", f"V2I_TLS_DIR={tls_dir}")
    common = ["--scenario", netns.SCENARIO, "--seed", "0", "--await-start", "--duration", str(RUN_S)]
    children["rsu"] = Child("rsu", netns._in(topo.rsu, "-m", "v2i", "rsu", "--listen", eps["rsu"], *common,
                                             "--zenoh-config", str(DEPLOY / "rsu.json5"), env=env))
    children["obu"] = Child("obu", netns._in(topo.obu, "-m", "v2i", "obu", "--listen", eps["obu"], *common,
                                             "--zenoh-config", str(DEPLOY / "obu.json5"), env=env))
    children["link"] = Child("link", netns._in(
        topo.link, "-m", "v2i", "link", "--config", str(link_config), "--rsu-connect", eps["rsu"],
        "--vehicle-connect", eps["obu"], "--control-listen", eps["control"], "--profile", "lte-v2x",
        *_control_flags(), "--zenoh-config", str(DEPLOY / "link.json5"), env=env))
    wait_ready(children.values())
    start_all(children.values())  # the emulator takes no time zero: it ignores the line
    return eps


def test_tls_acl_keep_an_intruder_out(tmp_path: Path) -> None:
    from v2i.security.tls import issue_tls

    token = secrets.token_hex(3)
    topo = netns.Topology(f"v2it-{token}-rsu", f"v2it-{token}-link", f"v2it-{token}-obu")
    pairs = [(topo.rsu, netns.RSU_ADDR, topo.link, netns.LINK_RSU_ADDR),
             (topo.link, netns.LINK_OBU_ADDR, topo.obu, netns.OBU_ADDR)]
    with netns._namespaces(topo, pairs, lo_up=(topo.obu,)):
        tls_dir = tmp_path / "tls"
        issue_tls(tls_dir, _names(), time.time_ns())
        children: dict = {}
        try:
            eps = _start(topo, tls_dir, netns._link_config(tmp_path), children)
            assert not netns._can_connect(topo.rsu, netns.OBU_ADDR, netns.OBU_PORT)  # still no bypass
            probe = netns._in(topo.obu, __file__, "probe", "--tls-dir", str(tls_dir), "--obu", eps["obu"],
                              "--control", eps["control"], "--rsu-id", _rsu_id(netns.SCENARIO))
            result = _run_probe(probe, timeout_s=READY_TIMEOUT_S + PROBE_S)
            print(json.dumps(result))  # pytest -s shows the counts
            for name, child in children.items():
                assert child.proc.poll() is None, f"{name} exited with {child.proc.returncode}"
        finally:
            for name in ("link", "rsu", "obu"):
                if name in children:
                    children[name].stop()
    assert result["genuine_lists_with_rsu_objects"] >= 3, result  # the genuine RSU keeps fusing
    assert result["clock_sync_samples"] > 0, result  # time queries and replies cross both ACLs
    assert result["no_cert"]["peers"] == 0, result  # (a) no client certificate: no connection
    intruder = result["vehicle_cert"]
    assert intruder["peers"] == 2 and intruder["ghosts_put"] > 0 and intruder["controls_put"] > 0, result
    for phase in ("no_cert", "vehicle_cert"):  # (a), (b): nothing delivered, nothing applied
        attempt = result[phase]
        assert attempt["ghosts_fused"] == 0 and attempt["fake_rsu_lists_accepted"] == 0, result
        assert attempt["control_applied"] == 0, result
    # positive controls: the same lists from a name the OBU's ACL admits arrive; the operator's control applies
    assert result["allowed"]["fake_rsu_lists_accepted"] > 0 and result["allowed"]["control_applied"] == 1, result


def _rsu_id(scenario: str) -> str:
    from v2i.sim.scenario import load_scenario

    return load_scenario(scenario).rsu.id


def _run_probe(argv: list[str], timeout_s: float) -> dict:
    """The probe's JSON result line; AssertionError with its output when it fails."""
    import subprocess

    proc = subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s, check=False)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    assert proc.returncode == 0 and lines, f"probe exit {proc.returncode}: {proc.stdout[-2000:]} {proc.stderr[-3000:]}"
    return json.loads(lines[-1])


# ----------------------------------------------------------------------------- the probe (in the OBU namespace)
def _session(config: Path | None, tls_dir: Path, connect: list[str]):
    """A peer session connecting to ``connect`` with this Zenoh site config (None: none)."""
    from v2i.runtime.transport import CONFIG_FILE_ENV, TLS_DIR_ENV, open_session

    os.environ[TLS_DIR_ENV] = str(tls_dir)
    os.environ.pop(CONFIG_FILE_ENV, None)
    if config is not None:
        os.environ[CONFIG_FILE_ENV] = str(config)
    return open_session(connect=connect)


def _tls_only(folder: Path, tls_dir: Path, name: str | None) -> Path:
    """An attacker's own config: TLS with the site CA and ``name``'s certificate (None: none), no ACL."""
    tls = {"root_ca_certificate": str(tls_dir / "tls-ca.pem"), "enable_mtls": True}
    if name is not None:
        for side in ("listen", "connect"):
            tls.update({f"{side}_certificate": str(tls_dir / f"{name}.pem"),
                        f"{side}_private_key": str(tls_dir / f"{name}.key")})
    path = folder / f"attacker-{name or 'nocert'}.json5"
    path.write_text(json.dumps({"transport": {"link": {"tls": tls}}}))
    return path


class Judge:
    """The observer (CN monitor): fused outputs judged for ghosts, OBU metrics, link stats."""

    def __init__(self, args, watch):
        from schemas.keys import link_stats, obu_metrics, obu_objects

        self.watch, self.fused, self.stats, self.metrics = watch, queue.Queue(), {}, {}
        self.session = _session(DEPLOY / "monitor.json5", args.tls_dir, [args.obu, args.control])
        self.subs = [self.session.declare_subscriber(obu_objects(VEHICLE_ID), lambda s: self.fused.put(s.payload.to_bytes())),
                     self.session.declare_subscriber(link_stats(LINK_ID), lambda s: self._json(self.stats, s)),
                     self.session.declare_subscriber(obu_metrics(VEHICLE_ID), lambda s: self._metrics(s))]
        self.ego, self.rsu_lists, self.ghosts = None, 0, 0

    @staticmethod
    def _json(into: dict, sample) -> None:
        into.update(json.loads(sample.payload.to_bytes()))

    def _metrics(self, sample) -> None:
        from schemas.codec import decode
        from schemas.messages import ObuMetrics

        self.metrics = decode(sample.payload.to_bytes(), ObuMetrics).model_dump()

    def drain(self, until: float) -> None:
        """Judge every fused list until ``until`` (monotonic s)."""
        from v2i.core.frames import Pose2D
        from schemas.codec import decode
        from schemas.limits import SOURCE_RSU
        from schemas.messages import FusedObjectList

        while (left := until - time.monotonic()) > 0:
            try:
                out = decode(self.fused.get(timeout=min(left, 0.1)), FusedObjectList)
            except queue.Empty:
                continue
            self.ego = Pose2D(out.ego_x, out.ego_y, out.ego_yaw)
            self.rsu_lists += bool(len(out.objects)) and bool((out.objects.column("sources").astype(int) & SOURCE_RSU).any())
            self.ghosts += self.watch.ghosts_in(out)

    def sync_samples(self) -> int:
        """The OBU's clock exchanges with its best-synchronised RSU, as its metrics last said."""
        return max((int(r.get("sync_samples", 0)) for r in self.metrics.get("rsus") or ()), default=0)

    def accepted(self, rsu_id: str) -> int:
        """Lists of ``rsu_id`` the OBU accepted, as its metrics last said."""
        return sum(int(r.get("messages_accepted", 0)) for r in self.metrics.get("rsus") or () if r.get("rsu_id") == rsu_id)

    def applied(self) -> int:
        return int((self.stats.get("control") or {}).get("applied", 0))

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.session.close()


def _wait_peers(session, count: int, timeout_s: float) -> int:
    deadline = time.monotonic() + timeout_s
    while len(list(session.info.peers_zid())) < count and time.monotonic() < deadline:
        time.sleep(0.05)
    return len(list(session.info.peers_zid()))


def _attack(judge: Judge, session, rsu_id: str, seq0: int, seconds: float, controls_max: int = 5) -> dict:
    """Ghost lists (on the victim RSU's key and, as ``FAKE_RSU``, on a key of their own: the OBU's
    metrics then show whether any arrived) and up to ``controls_max`` link outages from ``session``
    for ``seconds``; ghosts placed in the judge's watch."""
    from v2i.adversary.attack_messages import RSU_LATENCY_NS, ghost_list, ghost_xy
    from schemas.codec import encode
    from schemas.keys import link_control, rsu_objects
    from schemas.messages import LinkControl

    ghosts0, fake0, puts, controls = judge.ghosts, judge.accepted(FAKE_RSU), 0, 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        now_ns = time.time_ns()
        if judge.ego is not None:
            xy = ghost_xy(judge.ego)
            judge.watch.place(now_ns, xy)
            for rsu in (rsu_id, FAKE_RSU):
                session.put(rsu_objects(rsu), ghost_list(rsu, seq0 + puts, now_ns - RSU_LATENCY_NS, now_ns, xy))
            puts += 1
        if controls < controls_max:
            control = LinkControl(link_id=LINK_ID, seq=seq0 + controls, outage=True, duration_s=3600.0)
            session.put(link_control(LINK_ID), encode(control))
            controls += 1
        judge.drain(time.monotonic() + 1.0 / GHOST_RATE_HZ)
    judge.drain(time.monotonic() + 1.5)  # whatever is still in flight
    return {"ghosts_put": puts, "controls_put": controls, "ghosts_fused": judge.ghosts - ghosts0,
            "fake_rsu_lists_accepted": judge.accepted(FAKE_RSU) - fake0}


def _probe(args) -> dict:
    from v2i.adversary.attack_ghosts import GhostWatch

    folder = Path(args.tls_dir).parent
    judge = Judge(args, GhostWatch())
    result: dict = {}
    try:
        deadline = time.monotonic() + 25.0
        while (judge.rsu_lists < 3 or not judge.sync_samples()) and time.monotonic() < deadline:
            judge.drain(time.monotonic() + 0.2)
        result["genuine_lists_with_rsu_objects"] = judge.rsu_lists
        result["clock_sync_samples"] = judge.sync_samples()
        for name, key, cert in (("no_cert", "no_cert", None), ("vehicle_cert", "vehicle_cert", "vehicle-2")):
            session = _session(_tls_only(folder, Path(args.tls_dir), cert), args.tls_dir, [args.obu, args.control])
            try:
                peers = _wait_peers(session, 2, CONNECT_TIMEOUT_S)
                result[key] = {"peers": peers, **_attack(judge, session, args.rsu_id, 1_000_000, GHOST_SECONDS),
                               "control_applied": judge.applied()}
            finally:
                session.close()
        result["allowed"] = _allowed(judge, args, folder)
        result["genuine_lists_with_rsu_objects_end"] = judge.rsu_lists
    finally:
        judge.close()
    return result


def _allowed(judge: Judge, args, folder: Path) -> dict:
    """Positive controls: ghosts with the ``rsu`` name reach the fused output, ``operator`` control applies."""
    from schemas.codec import encode
    from schemas.keys import link_control
    from schemas.messages import LinkControl

    rsu = _session(_tls_only(folder, Path(args.tls_dir), "rsu"), args.tls_dir, [args.obu])
    try:
        _wait_peers(rsu, 1, CONNECT_TIMEOUT_S)
        ghosts = _attack(judge, rsu, args.rsu_id, 2_000_000, GHOST_SECONDS, controls_max=0)
        judge.drain(time.monotonic() + 1.5)  # the OBU's next metrics (1 Hz) count them
    finally:
        rsu.close()
    operator = _session(DEPLOY / "operator.json5", args.tls_dir, [args.control])
    try:
        _wait_peers(operator, 1, CONNECT_TIMEOUT_S)
        time.sleep(0.5)  # the emulator's control subscriber declaration reaches the operator's session
        operator.put(link_control(LINK_ID), encode(LinkControl(link_id=LINK_ID, seq=3_000_000, clear=True)))
        deadline = time.monotonic() + 5.0
        while judge.applied() < 1 and time.monotonic() < deadline:
            judge.drain(time.monotonic() + 0.2)
    finally:
        operator.close()
    return {**ghosts, "control_applied": judge.applied()}


if __name__ == "__main__":
    sys.path.insert(0, str(SRC))
    parser = argparse.ArgumentParser(description="the intruder and judge of test_netns_tls (OBU namespace)")
    parser.add_argument("command", choices=("probe",))
    parser.add_argument("--tls-dir", type=Path, required=True)
    parser.add_argument("--obu", required=True)
    parser.add_argument("--control", required=True)
    parser.add_argument("--rsu-id", required=True)
    print(json.dumps(_probe(parser.parse_args())), flush=True)
