"""One link emulator serving two vehicles, each on its own session and channel (real Zenoh,
loopback TCP, scouting off).

An "RSU" session listens and answers a time queryable; two "vehicle" sessions listen, each
on its own endpoint, and subscribe to the RSU's object lists; a LinkRelay in a thread
connects to all three and is their only path. Cutting one vehicle's channel (a LinkControl
naming it, or its distance beyond range) must leave the other's untouched.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from v2i.orchestration.children import READY_TIMEOUT_S
from link_emulator.config import LinkConfig
from link_emulator.control_client import ControlError, send_control
from link_emulator.relay import LinkRelay
from schemas.codec import encode
from schemas.keys import link_stats, obu_pose, rsu_objects, rsu_time
from schemas.messages import EgoPose, LinkControl
from v2i.runtime.transport import free_tcp_endpoint, open_session
from v2i.security.pki import load_signer
from v2i.security.site import write_site
from v2i.sim.clock import SystemClock

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60 + READY_TIMEOUT_S)]
DELIVERY_S = 5.0  # a few lists through an ideal relay on loopback (milliseconds each); generous for a busy machine

RSU_ID = "rsu1"
LINK_ID = "pairtest"
VEHICLES = ("car1", "car2")


@dataclass
class Vehicle:
    endpoint: str
    session: zenoh.Session
    objects: queue.Queue  # payloads this vehicle received


@dataclass
class Site:
    rsu_endpoint: str
    rsu: zenoh.Session
    vehicles: dict[str, Vehicle]
    stats: queue.Queue  # stats dicts heard by car1


def _answer_time(query: zenoh.Query) -> None:
    query.reply(query.key_expr, (query.payload.to_bytes() if query.payload is not None else b"") + b"|rsu")
    query.drop()


@pytest.fixture(scope="module")
def site() -> Iterator[Site]:
    rsu_ep = free_tcp_endpoint()
    rsu = open_session(listen=[rsu_ep])
    sessions, declared, stats = [rsu], [], queue.Queue()
    try:
        declared.append(rsu.declare_queryable(rsu_time(RSU_ID), _answer_time))
        vehicles = {}
        for vid in VEHICLES:
            ep, got = free_tcp_endpoint(), queue.Queue()
            session = open_session(listen=[ep])
            sessions.append(session)
            declared.append(session.declare_subscriber("v2x/rsu/*/objects",
                                                       lambda s, got=got: got.put(s.payload.to_bytes())))
            vehicles[vid] = Vehicle(ep, session, got)
        declared.append(vehicles["car1"].session.declare_subscriber(
            link_stats(LINK_ID), lambda s: stats.put(json.loads(s.payload.to_bytes()))))
        yield Site(rsu_ep, rsu, vehicles, stats)
    finally:
        for item in declared:
            item.undeclare()
        for session in reversed(sessions):
            session.close()


@contextmanager
def running_relay(site: Site, profile: str, control_listen: list[str] = (),
                  rsu_position: tuple[float, float] | None = None, pki: str | None = None) -> Iterator[LinkRelay]:
    config = LinkConfig(link_id=LINK_ID, rsu_connect=[site.rsu_endpoint], profile=profile, seed=3, pki=pki,
                        vehicles=[{"vehicle_id": vid, "connect": [v.endpoint]} for vid, v in site.vehicles.items()],
                        control_listen=list(control_listen), stats_period_s=0.2, rsu_position=rsu_position)
    relay = LinkRelay(config, SystemClock())
    stop = threading.Event()
    thread = threading.Thread(target=relay.run, args=(stop,), name="link-pairs")
    thread.start()
    try:
        assert relay.ready.wait(READY_TIMEOUT_S), "relay did not open its sessions"
        yield relay
    finally:
        stop.set()
        thread.join(5.0)
        assert not thread.is_alive(), "relay thread did not stop"


def _drain(q: queue.Queue) -> list:
    items = []
    while True:
        try:
            items.append(q.get_nowait())
        except queue.Empty:
            return items


def _wait_until_both_receive(site: Site, timeout_s: float = 8.0) -> None:
    """Put probes until each vehicle has received one (routes declared end to end)."""
    deadline, seen = time.monotonic() + timeout_s, set()
    while seen != set(VEHICLES):
        assert time.monotonic() < deadline, f"probes reached only {sorted(seen)}"
        site.rsu.put(rsu_objects(RSU_ID), b"probe")
        time.sleep(0.2)
        seen |= {vid for vid, v in site.vehicles.items() if _drain(v.objects)}


def _put_and_collect(site: Site, n: int, expect: tuple[str, ...]) -> dict[str, set[bytes]]:
    """Put n numbered lists; what each vehicle received of them once every vehicle of ``expect`` has
    all n (at most ``DELIVERY_S``). The relay decides a list for every channel at once, so a vehicle
    cut off would have had its copies by then; the tests then check the relay's counts of them."""
    for v in site.vehicles.values():
        _drain(v.objects)
    sent = [b"list-%d" % i for i in range(n)]
    for payload in sent:
        site.rsu.put(rsu_objects(RSU_ID), payload)
        time.sleep(0.005)  # paced, not a wait: a burst of puts is not what the test is about
    got: dict[str, set[bytes]] = {vid: set() for vid in site.vehicles}
    deadline = time.monotonic() + DELIVERY_S
    while any(len(got[vid]) < n for vid in expect) and time.monotonic() < deadline:
        for vid, v in site.vehicles.items():
            try:
                got[vid].add(v.objects.get(timeout=0.02))
            except queue.Empty:
                pass
    return {vid: {*got[vid], *_drain(v.objects)} & set(sent) for vid, v in site.vehicles.items()}


def _answered(site: Site, vid: str, timeout_s: float = 1.0) -> bool:
    replies = site.vehicles[vid].session.get(rsu_time(RSU_ID), payload=b"t1", timeout=timeout_s)
    return any(r.ok is not None and r.ok.payload.to_bytes() == b"t1|rsu" for r in replies)


def _stats_where(site: Site, accept, timeout_s: float = 5.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while (remaining_s := deadline - time.monotonic()) > 0:
        try:
            stats = site.stats.get(timeout=remaining_s)
        except queue.Empty:
            break
        if accept(stats):
            return stats
    pytest.fail("no stats message satisfied the condition")


def _pair(stats: dict, vid: str) -> dict:
    return next(p for p in stats["pairs"] if p["vehicle_id"] == vid)


def test_a_control_naming_one_vehicle_cuts_only_its_channel(site: Site, tmp_path) -> None:
    control_ep = free_tcp_endpoint()
    pki = str(write_site(tmp_path, time.time_ns()))
    operator = load_signer(pki, "operator")  # the emulator applies only an operator's signed control
    with running_relay(site, "ideal", control_listen=[control_ep], pki=pki):
        _wait_until_both_receive(site)
        assert all(_answered(site, vid, 2.0) for vid in VEHICLES)
        result = send_control([control_ep], LinkControl(link_id=LINK_ID, seq=11, vehicle_id="car2", outage=True,
                                                        duration_s=30.0), 5.0, operator)
        assert result == "outage on both for 30 s (vehicle car2)"
        got = _put_and_collect(site, 20, expect=("car1",))
        assert len(got["car1"]) == 20 and got["car2"] == set()
        assert _answered(site, "car1") and not _answered(site, "car2", 0.5)
        with pytest.raises(ControlError, match="rejected it \\(unknown_vehicle\\)"):
            send_control([control_ep], LinkControl(link_id=LINK_ID, seq=12, vehicle_id="car9", clear=True), 5.0,
                         operator)
        # a stats message from after car1's reply and car9's rejection (older ones may still be queued)
        stats = _stats_where(site, lambda s: _pair(s, "car2")["uplink"]["dropped"] >= 1 and s["control"]["rejected"])
        car1, car2 = _pair(stats, "car1"), _pair(stats, "car2")
        assert car2["downlink"]["delivered"] == car1["downlink"]["delivered"] - 20 - 1  # the lists, the reply
        assert car1["downlink"]["dropped"] == 0
        assert stats["downlink"]["received"] == car1["downlink"]["received"] + car2["downlink"]["received"]
        assert stats["control"]["applied"] == 1 and stats["control"]["rejected"] == {"unknown_vehicle": 1}
        send_control([control_ep], LinkControl(link_id=LINK_ID, seq=13, clear=True), 5.0, operator)
        got = _put_and_collect(site, 5, expect=VEHICLES)
        assert len(got["car1"]) == 5 and len(got["car2"]) == 5


def _put_pose_until_heard(site: Site, vid: str, x_m: float, distance_m: float) -> None:
    pose = encode(EgoPose(vehicle_id=vid, t_ns=time.time_ns(), x=x_m, y=0.0))
    deadline = time.monotonic() + 8.0
    while time.monotonic() < deadline:
        site.vehicles[vid].session.put(obu_pose(vid), pose)
        try:
            stats = site.stats.get(timeout=0.3)
        except queue.Empty:
            continue
        if _pair(stats, vid)["pose"]["distance_m"] == pytest.approx(distance_m):
            return
    pytest.fail(f"the relay never placed {vid} {distance_m} m from the RSU")


def test_each_vehicle_has_its_own_distance(site: Site, tmp_path: Path) -> None:
    profile = tmp_path / "ranged.yaml"
    profile.write_text("name: ranged\nuplink: {delay_ms: 0}\ndownlink: {delay_ms: 0, range_m: 100.0}\n")
    with running_relay(site, str(profile), rsu_position=(0.0, 0.0)):
        _wait_until_both_receive(site)
        _put_pose_until_heard(site, "car1", 40.0, 40.0)  # in range
        _put_pose_until_heard(site, "car2", 500.0, 500.0)  # beyond range: everything lost
        got = _put_and_collect(site, 10, expect=("car1",))
        assert len(got["car1"]) == 10 and got["car2"] == set()
        stats = _stats_where(site, lambda s: _pair(s, "car2")["downlink"]["dropped"] >= 10)
        assert _pair(stats, "car2")["pose"]["vehicle_id"] == "car2"
        assert _pair(stats, "car1")["downlink"]["dropped"] == 0
        assert stats["pose"]["received"] >= 2 and stats["pose"]["distance_m"] is None
