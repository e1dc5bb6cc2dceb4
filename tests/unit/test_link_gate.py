"""What peers can make the link emulator hold, and which poses move its vehicle."""

from link_emulator.config import LinkConfig
from link_emulator.gate import Gate, InFlight
from link_emulator.gate import VehiclePosition
from schemas.messages import EgoPose
from v2i.sim.clock import SimClock

T0 = 1_767_225_600 * 10**9
S = 1_000_000_000
EP = ["tcp/127.0.0.1:7447"]


def config(**fields) -> LinkConfig:
    return LinkConfig(rsu_connect=EP, vehicle_connect=EP, **fields)


def test_gate_refuses_large_fast_and_piled_up_arrivals():
    clock = SimClock(T0)
    gate = Gate(config(max_message_bytes=2048, source_rate_hz=10.0, source_burst=2, max_pending_arrivals=16,
                       total_bytes_per_s=1e6), clock)
    assert not gate.admit("a", 4096)
    assert [gate.admit("a", 10) for _ in range(3)] == [True, True, False]  # a's burst, then its rate
    assert all(gate.admit(f"k{k}", 10) for k in range(14))
    assert not gate.admit("c", 10)  # sixteen arrivals pending
    gate.done()
    assert gate.admit("c", 10)
    assert gate.snapshot() == {"too_large": 1, "rate_limited": 1, "overflow": 1}


def test_gate_byte_budget_covers_all_keys_together():
    clock = SimClock(T0)
    gate = Gate(config(total_bytes_per_s=1e5, source_rate_hz=1e6, source_burst=1000), clock)
    admitted = sum(gate.admit(f"key{k}", 20_000) or 0 for k in range(10))  # 200 kB from 10 keys at once
    assert admitted == 5 and gate.snapshot() == {"bytes_limited": 5}
    clock.t_ns += S
    assert gate.admit("key0", 20_000)


def test_in_flight_is_capped_in_messages_and_bytes():
    cfg = config(max_in_flight=16, max_in_flight_bytes=1 << 16)
    flight = InFlight()
    assert all(flight.reserve(1000, cfg) for _ in range(16)) and not flight.reserve(1, cfg)
    flight.release(1000)
    assert not flight.reserve(1 << 16, cfg) and flight.reserve(100, cfg)
    assert (flight.messages, flight.bytes) == (16, 15 * 1000 + 100)


def pose(x: float, t_s: float, vehicle_id: str = "ego") -> EgoPose:
    return EgoPose(vehicle_id=vehicle_id, t_ns=T0 + round(t_s * S), x=x, y=0.0)


def test_only_the_emulated_vehicle_moves_and_only_plausibly():
    position = VehiclePosition(vehicle_id=None, max_speed_mps=100.0)
    assert position.take(pose(0.0, 0.0))  # the first id heard is the emulated vehicle
    assert not position.take(pose(5.0, 0.1, vehicle_id="intruder"))
    assert not position.take(pose(1e6, 0.2))  # 1000 km in 0.2 s
    assert not position.take(pose(1.0, -1.0))  # older than the last
    assert not position.take(pose(0.0, 0.0))  # the same pose again
    assert position.take(pose(9.0, 0.1))  # 90 m/s
    assert position.take(pose(990.0, 10.0))  # a re-localisation, taken once 100 m/s allows it
    assert position.distance_m((1000.0, 0.0)) == 10.0
    assert dict(position.refused) == {"other_vehicle": 1, "implausible": 2, "duplicate": 1}
    assert position.received == 3 and position.as_dict(None)["vehicle_id"] == "ego"
