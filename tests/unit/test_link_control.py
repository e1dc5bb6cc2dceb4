"""Runtime link control without Zenoh: ``v2i link set`` options -> LinkControl, and the
relay's handling of control payloads (applied, or counted as rejected by reason)."""

from __future__ import annotations

import pytest

from link_emulator.config import LinkConfig
from link_emulator.control_client import SetAction, control_from_action
from link_emulator.relay import LinkRelay
from schemas.codec import encode
from schemas.messages import LinkControl
from v2i.sim.clock import SystemClock

EP = "tcp/127.0.0.1:1"


def test_profile_and_clear_map_to_their_actions():
    assert control_from_action("l1", SetAction(profile="dsrc")) == LinkControl(link_id="l1", profile="dsrc")
    assert control_from_action("l1", SetAction(clear=True), seq=7) == LinkControl(link_id="l1", clear=True, seq=7)


def test_outage_lasts_its_seconds_on_its_direction():
    control = control_from_action("l1", SetAction(outage_s=10.0, direction="downlink"))
    assert control.outage and control.duration_s == 10.0 and control.direction == "downlink"


@pytest.mark.parametrize(
    ("action", "field", "value"),
    [
        (SetAction(delay_spike_ms=300.0, for_s=2.0), "extra_delay_ms", 300.0),
        (SetAction(loss_probability=0.5, for_s=2.0), "loss_probability", 0.5),
        (SetAction(bandwidth_kbps=64.0, for_s=2.0), "bandwidth_kbps", 64.0),
    ],
)
def test_timed_impairments_take_their_duration_from_for(action, field, value):
    control = control_from_action("l1", action)
    assert getattr(control, field) == value and control.duration_s == 2.0 and not control.outage


@pytest.mark.parametrize(
    ("action", "message"),
    [
        (SetAction(delay_spike_ms=300.0), "--delay-spike needs --for"),
        (SetAction(outage_s=3.0, for_s=2.0), "--for applies to"),
        (SetAction(loss_probability=1.5, for_s=2.0), "loss_probability"),
        (SetAction(profile="../etc/passwd"), "profile"),
    ],
)
def test_wrong_options_are_named(action, message):
    with pytest.raises(ValueError, match=message):
        control_from_action("l1", action)


@pytest.fixture
def relay() -> LinkRelay:
    """An emulator applying unsigned control (its authentication: tests/unit/test_link_control_auth.py)."""
    config = LinkConfig(link_id="l1", rsu_connect=[EP], vehicle_connect=[EP], profile="ideal", insecure_control=True)
    return LinkRelay(config, SystemClock())


def test_relay_applies_a_control_and_reports_it_in_the_stats(relay):
    relay._control_arrival(encode(LinkControl(link_id="l1", seq=5, profile="dsrc")), 0)
    relay._control_arrival(encode(LinkControl(link_id="l1", seq=6, outage=True, duration_s=1.0)), 0)
    stats = relay.stats_snapshot(0)
    assert stats["profile"] == "dsrc"
    assert stats["control"]["applied"] == 2 and stats["control"]["rejected"] == {}
    assert [o["seq"] for o in stats["control"]["recent"]] == [5, 6]
    assert relay.pairs[0].model.downlink.transmit(500_000_000, 100) is None  # inside the outage
    assert relay.pairs[0].model.downlink.transmit(1_500_000_000, 100) is not None


def test_relay_counts_bad_controls_by_reason_and_changes_nothing(relay):
    relay._control_arrival(b"not msgpack at all", 0)
    relay._control_arrival(encode(LinkControl(link_id="other", seq=1, clear=True)), 0)
    relay._control_arrival(encode(LinkControl(link_id="l1", seq=2, profile="no-such-profile")), 0)
    relay._control_arrival(encode(LinkControl(link_id="l1", seq=3, profile="no-such-profile")), 0)
    control = relay.stats_snapshot(0)["control"]
    assert control["applied"] == 0
    assert control["rejected"] == {"codec_malformed": 1, "wrong_link_id": 1, "unknown_profile": 2}
    assert control["recent"][-1] == {"seq": 3, "rejected": "unknown_profile", "error": control["recent"][-1]["error"]}
    assert relay.profile.name == "ideal"
