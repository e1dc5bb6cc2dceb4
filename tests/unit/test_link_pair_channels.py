"""RSU-vehicle pairs of one link emulator, without Zenoh: config forms and bounds, ``--vehicle``
parsing, per-pair seeds and draws, controls naming a vehicle, and the stats over pairs."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
from pydantic import ValidationError

from link_emulator.channel import LinkModel
from link_emulator.cli import parse_vehicle
from link_emulator.config import MAX_VEHICLES, LinkConfig
from link_emulator.control_client import SetAction, control_from_action
from link_emulator.pair import pair_seed
from link_emulator.profile import load_profile
from link_emulator.relay import LinkRelay
from schemas.codec import encode
from schemas.messages import EgoPose, LinkControl
from v2i.sim.clock import SystemClock

EP = ["tcp/127.0.0.1:1"]
S = 1_000_000_000
T0 = 1_767_225_600 * S


def vehicles(*ids: str) -> list[dict]:
    return [{"vehicle_id": vid, "connect": [f"tcp/127.0.0.1:{2000 + k}"]} for k, vid in enumerate(ids)]


def relay_for(*ids: str, profile: str = "lte-v2x", seed: int = 7) -> LinkRelay:
    return LinkRelay(LinkConfig(link_id="l1", rsu_connect=EP, vehicles=vehicles(*ids), profile=profile, seed=seed,
                                rsu_position=(0.0, 0.0), insecure_control=True), SystemClock())  # unsigned control


def downlink_draws(model: LinkModel, n: int = 200) -> list[int | None]:
    return [model.downlink.transmit(k * S // 10, 500) for k in range(n)]


def test_parse_vehicle_takes_an_id_and_endpoints():
    assert parse_vehicle("car1=tcp/127.0.0.1:7448") == {"vehicle_id": "car1", "connect": ["tcp/127.0.0.1:7448"]}
    assert parse_vehicle("c=tcp/a:1, tcp/b:2")["connect"] == ["tcp/a:1", "tcp/b:2"]
    for bad in ("car1", "=tcp/a:1", "car1=", "car1=,"):
        with pytest.raises(argparse.ArgumentTypeError, match="ID=EP"):
            parse_vehicle(bad)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({}, "exactly one of them"),
        ({"vehicle_connect": EP, "vehicles": vehicles("a")}, "exactly one of them"),
        ({"vehicles": vehicles("a", "b", "a")}, "unique, got a twice"),
        ({"vehicles": vehicles("a"), "vehicle_id": "a"}, "belongs to the one-vehicle form"),
        ({"vehicles": vehicles(*(f"v{k}" for k in range(MAX_VEHICLES + 1)))}, f"at most {MAX_VEHICLES}"),
        ({"vehicles": [{"vehicle_id": "a/b", "connect": EP}]}, "vehicle_id"),
        ({"vehicles": [{"vehicle_id": "a", "connect": []}]}, "connect"),
    ],
)
def test_bad_vehicle_sides_are_refused_by_name(fields, message):
    with pytest.raises(ValidationError, match=message):
        LinkConfig(rsu_connect=EP, **fields)


def test_the_one_vehicle_form_is_one_pair_seeded_as_before():
    config = LinkConfig(rsu_connect=EP, vehicle_connect=EP, seed=7)
    relay = LinkRelay(config, SystemClock())
    assert [p.side.vehicle_id for p in relay.pairs] == [None]
    assert downlink_draws(relay.pairs[0].model) == downlink_draws(LinkModel(load_profile("lte-v2x"), 7))
    assert len(relay_for(*(f"v{k}" for k in range(MAX_VEHICLES))).pairs) == MAX_VEHICLES


def test_pair_seeds_depend_on_the_vehicle_only():
    assert pair_seed(7, "car1") == pair_seed(7, "car1")
    assert len({pair_seed(7, "car1"), pair_seed(7, "car2"), pair_seed(8, "car1")}) == 3
    # car2's draws are the same whether or not car1 is served, and differ from car1's
    alone, both = relay_for("car2").pairs[0], relay_for("car1", "car2").pairs[1]
    assert downlink_draws(alone.model) == downlink_draws(both.model)
    car1 = relay_for("car1", "car2").pairs[0]
    assert downlink_draws(car1.model) != downlink_draws(relay_for("car1", "car2").pairs[1].model)


def test_pair_losses_are_independent():
    """Two pairs of a 50 % Bernoulli-loss profile: each loses about half, their losses uncorrelated."""
    relay = relay_for("car1", "car2", profile="ideal")
    for pair in relay.pairs:
        pair.model.add_impairment(0, 10**6 * S, loss_probability=0.5)
    lost = np.array([[p.model.downlink.transmit(k * S // 10, 100) is None for p in relay.pairs] for k in range(4000)])
    assert lost.mean(axis=0) == pytest.approx([0.5, 0.5], abs=0.03)
    assert abs(np.corrcoef(lost[:, 0], lost[:, 1])[0, 1]) < 0.05


def test_a_control_naming_a_vehicle_changes_only_its_pair():
    relay = relay_for("car1", "car2", profile="ideal")
    relay._control_arrival(encode(LinkControl(link_id="l1", seq=1, vehicle_id="car2", outage=True,
                                              duration_s=1.0)), 0)
    relay._control_arrival(encode(LinkControl(link_id="l1", seq=2, vehicle_id="car1", profile="dsrc")), 0)
    relay._control_arrival(encode(LinkControl(link_id="l1", seq=3, vehicle_id="car3", clear=True)), 0)
    car1, car2 = relay.pairs
    assert car1.model.downlink.transmit(S // 2, 100) is not None
    assert car2.model.downlink.transmit(S // 2, 100) is None  # inside car2's outage
    assert car2.model.downlink.transmit(3 * S // 2, 100) is not None
    stats = relay.stats_snapshot(0)
    assert stats["profile"] == "mixed" and [p["profile"] for p in stats["pairs"]] == ["dsrc", "ideal"]
    assert stats["control"]["recent"][0]["result"] == "outage on both for 1 s (vehicle car2)"
    assert stats["control"]["rejected"] == {"unknown_vehicle": 1}


def test_a_control_without_a_vehicle_changes_every_pair():
    relay = relay_for("car1", "car2", profile="ideal")
    relay._control_arrival(encode(LinkControl(link_id="l1", seq=1, outage=True, duration_s=1.0)), 0)
    assert all(p.model.downlink.transmit(S // 2, 100) is None for p in relay.pairs)


def test_stats_sum_the_pairs_and_list_each():
    relay = relay_for("car1", "car2", profile="ideal")
    car1, car2 = relay.pairs
    car1.downlink.received, car1.downlink.delivered = 5, 4
    car1.downlink.delay_ms.add(10.0)
    car2.downlink.received, car2.downlink.dropped = 3, 3
    car2.downlink.delay_ms.add(30.0)
    car2.position.take(EgoPose(vehicle_id="car2", t_ns=T0, x=3.0, y=4.0))
    car2.position.take(EgoPose(vehicle_id="car1", t_ns=T0 + S, x=3.0, y=4.0))  # not car2's pose
    stats = relay.stats_snapshot(0)
    assert stats["downlink"]["received"] == 8 and stats["downlink"]["delivered"] == 4
    assert stats["downlink"]["dropped"] == 3
    assert stats["downlink"]["delay_ms"] == {"count": 2, "mean": 20.0, "min": 10.0, "max": 30.0}
    assert [p["vehicle_id"] for p in stats["pairs"]] == ["car1", "car2"]
    assert stats["pairs"][1]["pose"]["distance_m"] == 5.0 and stats["pairs"][0]["pose"]["distance_m"] is None
    assert stats["pose"]["refused"] == {"other_vehicle": 1} and stats["pose"]["received"] == 1


def test_link_set_vehicle_names_it_in_the_control():
    control = control_from_action("l1", SetAction(outage_s=2.0, vehicle_id="car2"))
    assert control.vehicle_id == "car2" and control.outage
    with pytest.raises(ValueError, match="vehicle_id"):
        control_from_action("l1", SetAction(clear=True, vehicle_id="no/such"))


def test_vehicle_keys_have_a_rate_bucket_per_pair():
    """Every vehicle asks v2x/rsu/{id}/time and gets replies on it: one vehicle at its burst must not
    starve the others (20 OBUs at 10 Hz exceed one key's 100/s)."""
    relay = relay_for("car1", "car2")
    gate = relay._gate
    key = "v2x/rsu/rsu1/time"
    car1, car2 = relay.pairs
    burst = relay.config.source_burst
    assert all(gate.admit(car1.gate_key(key), 10) for _ in range(burst))
    assert not gate.admit(car1.gate_key(key), 10)  # car1's bucket is empty
    assert gate.admit(car2.gate_key(key), 10) and gate.admit(car2.gate_key(f"reply {key}"), 10)
    assert gate.snapshot() == {"rate_limited": 1}
