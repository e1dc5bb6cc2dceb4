"""The V2V link emulator (``link_emulator.v2v_relay``) between three vehicle sessions (real
Zenoh, loopback TCP, scouting off): a vehicle's messages reach every other vehicle through
its own channel, never itself, and no vehicle can speak for another; a control naming one
vehicle cuts only the pairs it is in; distances come from each vehicle's poses."""

from __future__ import annotations

import json
import queue
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import pytest
import zenoh

from v2i.orchestration.children import READY_TIMEOUT_S
from link_emulator.config import LinkConfig
from link_emulator.control_client import send_control
from link_emulator.v2v_relay import V2vRelay
from schemas.codec import encode
from schemas.keys import link_stats, obu_pose, v2v_objects
from schemas.messages import EgoPose, LinkControl
from v2i.runtime.transport import free_tcp_endpoint, open_session
from v2i.sim.clock import SystemClock

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60 + READY_TIMEOUT_S)]
DELIVERY_S = 5.0  # a few messages through an ideal relay on loopback (milliseconds each); generous for a busy machine

LINK_ID = "v2vtest"
VEHICLES = ("car1", "car2", "car3")


@dataclass
class Car:
    endpoint: str
    session: zenoh.Session
    heard: queue.Queue  # (key, payload) of v2x/v2v/** samples that are not its own


@pytest.fixture(scope="module")
def cars() -> Iterator[dict[str, Car]]:
    sessions, declared, cars = [], [], {}
    try:
        for vid in VEHICLES:
            ep, heard = free_tcp_endpoint(), queue.Queue()
            session = open_session(listen=[ep])
            sessions.append(session)
            own = f"v2x/v2v/{vid}/"
            declared.append(session.declare_subscriber(
                "v2x/v2v/**", lambda s, h=heard, own=own: None if str(s.key_expr).startswith(own)
                else h.put((str(s.key_expr), s.payload.to_bytes()))))
            cars[vid] = Car(ep, session, heard)
        yield cars
    finally:
        for item in declared:
            item.undeclare()
        for session in reversed(sessions):
            session.close()


@contextmanager
def running(cars: dict[str, Car], control_listen: list[str] = (), profile: str = "ideal") -> Iterator[V2vRelay]:
    config = LinkConfig(link_id=LINK_ID, v2v=True, profile=profile, seed=5, stats_period_s=0.2,
                        vehicles=[{"vehicle_id": vid, "connect": [c.endpoint]} for vid, c in cars.items()],
                        control_listen=list(control_listen), insecure_control=True)  # unsigned control (lab)
    relay = V2vRelay(config, SystemClock())
    stop = threading.Event()
    thread = threading.Thread(target=relay.run, args=(stop,), name="v2v-relay")
    thread.start()
    try:
        assert relay.ready.wait(READY_TIMEOUT_S), "relay did not open its sessions"
        _wait_routes(cars)
        yield relay
    finally:
        stop.set()
        thread.join(5.0)
        assert not thread.is_alive(), "relay thread did not stop"


def _drain(q: queue.Queue) -> list:
    out = []
    while True:
        try:
            out.append(q.get_nowait())
        except queue.Empty:
            return out


def _wait_routes(cars: dict[str, Car], timeout_s: float = 10.0) -> None:
    """Every vehicle probes until every other has heard it (routes declared end to end)."""
    deadline, seen = time.monotonic() + timeout_s, set()
    want = {(a, b) for a in VEHICLES for b in VEHICLES if a != b}
    while seen != want:
        assert time.monotonic() < deadline, f"probes crossed only {sorted(seen)}"
        for vid, car in cars.items():
            car.session.put(v2v_objects(vid), b"probe")
        time.sleep(0.2)
        for vid, car in cars.items():
            seen |= {(key.split("/")[2], vid) for key, _ in _drain(car.heard)}


def _put_and_collect(cars: dict[str, Car], sender: str, key: str, n: int, expect: tuple[str, ...] = (),
                     marker_to: str | None = None) -> dict[str, list]:
    """Put n numbered messages from ``sender`` on ``key``; what each vehicle heard of them once every
    vehicle of ``expect`` heard all n, and ``marker_to`` (if given) heard a marker the sender puts on its
    own key after them (the relay's path for them, in order: whatever was going to arrive has), at
    most ``DELIVERY_S``."""
    for car in cars.values():
        _drain(car.heard)
    sent = [b"msg-%d" % i for i in range(n)]
    for payload in sent:
        cars[sender].session.put(key, payload)
        time.sleep(0.005)  # paced, not a wait: a burst of puts is not what the test is about
    marker = b"marker-%d" % time.monotonic_ns()
    if marker_to is not None:
        cars[sender].session.put(v2v_objects(sender), marker)
    heard: dict[str, list] = {vid: [] for vid in cars}
    deadline = time.monotonic() + DELIVERY_S
    while time.monotonic() < deadline and (any(len([p for p in heard[v] if p in sent]) < n for v in expect)
                                           or (marker_to is not None and marker not in heard[marker_to])):
        for vid, car in cars.items():
            try:
                heard[vid].append(car.heard.get(timeout=0.02)[1])
            except queue.Empty:
                pass
    if marker_to is not None:
        assert marker in heard[marker_to], f"{marker_to} never heard {sender}'s marker"
    return {vid: [p for p in [*heard[vid], *(p for _, p in _drain(c.heard))] if p in sent] for vid, c in cars.items()}


def test_a_vehicle_reaches_every_other_through_its_own_channel_and_never_itself(cars):
    deliveries = []
    with running(cars) as relay:
        relay._observer = deliveries.append
        got = _put_and_collect(cars, "car1", v2v_objects("car1"), 10, expect=("car2", "car3"), marker_to="car3")
        assert len(got["car2"]) == 10 and len(got["car3"]) == 10 and got["car1"] == []
        assert all(d.vehicle_id != "car1" for d in deliveries if d.key.startswith("v2x/v2v/car1/"))
        assert sorted(relay.pairs) == sorted((a, b) for a in VEHICLES for b in VEHICLES if a != b)
        # car1 cannot speak for car2: the relay takes only v2x/v2v/car1/** from car1's session
        got = _put_and_collect(cars, "car1", v2v_objects("car2"), 5, marker_to="car3")
        assert got["car3"] == []


def test_a_control_naming_one_vehicle_cuts_only_its_pairs(cars):
    control_ep = free_tcp_endpoint()
    stats: queue.Queue = queue.Queue()
    with running(cars, [control_ep]):
        sub = cars["car2"].session.declare_subscriber(link_stats(LINK_ID),
                                                      lambda s: stats.put(json.loads(s.payload.to_bytes())))
        try:
            result = send_control([control_ep], LinkControl(link_id=LINK_ID, seq=21, vehicle_id="car3", outage=True,
                                                            duration_s=30.0), 5.0)
            assert result == "outage on both for 30 s (vehicle car3)"
            got = _put_and_collect(cars, "car1", v2v_objects("car1"), 10, expect=("car2",), marker_to="car2")
            assert len(got["car2"]) == 10 and got["car3"] == []
            got = _put_and_collect(cars, "car3", v2v_objects("car3"), 5)  # car3's pairs are cut: checked below
            assert got["car1"] == [] and got["car2"] == []
            # distances from the vehicles' poses, per pair
            for vid, x in (("car1", 0.0), ("car2", 30.0)):
                cars[vid].session.put(obu_pose(vid), encode(EgoPose(vehicle_id=vid, t_ns=time.time_ns(), x=x, y=0.0)))
            # a stats message (every 0.2 s) from after both poses and car3's 5 messages (dropped on both its pairs)
            deadline, pair = time.monotonic() + DELIVERY_S, {}
            while not (pair and pair["car1>car2"]["distance_m"] == pytest.approx(30.0)
                       and pair["car3>car1"]["dropped"] >= 5 and pair["car3>car2"]["dropped"] >= 5):
                try:
                    s = stats.get(timeout=deadline - time.monotonic())
                except (queue.Empty, ValueError):  # ValueError: the deadline has passed (a negative timeout)
                    pytest.fail(f"no stats message with car1 and car2 30 m apart and car3's 5 dropped: {pair}")
                pair = {f"{p['from']}>{p['to']}": p for p in s["pairs"]}
            assert pair["car1>car3"]["distance_m"] is None  # car3's pose never heard
            assert pair["car1>car3"]["dropped"] >= 10 and pair["car1>car2"]["dropped"] == 0
            assert s["mode"] == "v2v" and s["control"]["applied"] == 1
        finally:
            sub.undeclare()


def test_v2v_config_needs_two_vehicles_and_no_rsu_side():
    ok = {"v2v": True, "vehicles": [{"vehicle_id": "a", "connect": ["tcp/127.0.0.1:1"]},
                                    {"vehicle_id": "b", "connect": ["tcp/127.0.0.1:2"]}]}
    assert LinkConfig(**ok).v2v
    with pytest.raises(ValueError, match="at least two vehicles"):
        LinkConfig(**{**ok, "vehicles": ok["vehicles"][:1]})
    with pytest.raises(ValueError, match="no rsu_connect"):
        LinkConfig(**ok, rsu_connect=["tcp/127.0.0.1:3"])
    with pytest.raises(ValueError, match="rsu_connect"):
        LinkConfig(vehicles=ok["vehicles"])
