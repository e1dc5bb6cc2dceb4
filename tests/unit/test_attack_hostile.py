"""The opt-in kinds of ``v2i attack`` (v2i.adversary.attack_hostile): their options, the flood's pacing,
and what the relay rows read from the OBU's metrics."""

from __future__ import annotations

import argparse
import time

import numpy as np
import pytest

from schemas.messages import EgoPose, ObuMetrics, RsuLinkStatus
from v2i.adversary.attack import check_kinds
from v2i.adversary.attack_hostile import _clock_samples, _first_sync_s, rsu_status
from v2i.adversary.attack_live import AttackRun
from v2i.adversary.attack_messages import FLOOD_VARIANTS, AttackMessages
from v2i.cli import main

S = 1_000_000_000
T0_NS = 1_800_000_000 * S  # the window's time base (a plausible Unix time)


def _args(**over) -> argparse.Namespace:
    values = dict(kinds="flood", control=None, count=10, rate_hz=30.0, time_burst=3, ready_timeout=5.0,
                  flood_rate_hz=500.0, flood_s=20.0, time_s=40.0, time_delay_ms=100.0, from_start=False)
    values.update(over)
    return argparse.Namespace(**values)


def test_the_opt_in_kinds_and_their_options_are_checked():
    assert check_kinds(_args(kinds="time_doubled,flood", from_start=True)) == ["time_doubled", "flood"]
    for bad, words in [(dict(kinds="flood,flood"), "each kind once"), (dict(flood_rate_hz=0.0), "--flood-rate-hz"),
                       (dict(flood_rate_hz=50_000.0), "--flood-rate-hz"), (dict(time_s=0.0), "--time-s"),
                       (dict(time_delay_ms=-1.0), "--time-delay-ms"),
                       (dict(kinds="flood,time_doubled", from_start=True), "--from-start: the first kind")]:
        with pytest.raises(ValueError, match=words):
            check_kinds(_args(**bad))


def test_the_command_line_refuses_a_bad_flood_rate(capsys):
    code = main(["attack", "--connect", "tcp/127.0.0.1:9", "--sniff", "tcp/127.0.0.1:9", "--pki", "/nonexistent",
                 "--kinds", "flood", "--flood-rate-hz", "0"])
    assert code == 2 and "--flood-rate-hz must be in (0, 20000]" in capsys.readouterr().err


class _Publisher:
    def __init__(self):
        self.sent: list[tuple[float, bytes]] = []

    def put(self, data: bytes) -> None:
        self.sent.append((time.monotonic(), data))


def test_the_flood_keeps_its_rate_and_sends_each_variant_in_turn(tmp_path):
    from v2i.security.attacker_keys import load_attacker_keys, prepare_attacker_pki
    from v2i.security.site import write_site

    write_site(tmp_path, time.time_ns(), rsu_ids=["rsu1"], vehicle_ids=["ego"])
    prepare_attacker_pki(tmp_path, time.time_ns(), "rsu1")
    run = AttackRun(argparse.Namespace(seed=0, rsu_id="rsu1", vehicle_id="ego", link_id="link1"), ["flood"], None)
    run.messages = AttackMessages("rsu1", load_attacker_keys(tmp_path, "rsu1"), np.random.default_rng(0), b"d" * 32)
    run.publisher, run.pose = _Publisher(), EgoPose(vehicle_id="ego", t_ns=time.time_ns(), x=1.0, y=2.0, yaw=0.5)
    sent, send_s = run._send_flood(400.0, 0.5)
    assert 0.5 <= send_s < 0.6 and sum(sent.values()) == len(run.publisher.sent)
    assert 190 <= sum(sent.values()) <= 202  # 400/s for 0.5 s: ~200, never ahead of the schedule
    assert max(sent.values()) - min(sent.values()) <= 1 and set(sent) == set(FLOOD_VARIANTS)
    assert len(run.watch._ghosts) >= 20  # the ghost placement follows the flood (one per 20 ms payload)


def _metrics(t_s: float, offset_ms: float | None, uncertainty_ms: float = 5.0) -> ObuMetrics:
    status = RsuLinkStatus(rsu_id="rsu1", clock_offset_ns=None if offset_ms is None else round(offset_ms * 1e6),
                           clock_uncertainty_ns=round(uncertainty_ms * 1e6))
    return ObuMetrics(vehicle_id="ego", t_ns=T0_NS + round(t_s * S), rsus=(status,))


def test_first_sync_and_the_clock_samples_of_a_window():
    window = [_metrics(10.0 + 0.1 * k, None if k < 5 else 350.0 + 0.01 * k) for k in range(40)]
    assert _first_sync_s(window, "rsu1", since_ns=T0_NS + 9 * S) == 1.5  # the first estimate at 10.5 s
    assert _first_sync_s(window[:5], "rsu1", since_ns=T0_NS + 9 * S) is None
    assert _first_sync_s(window, "rsu1", since_ns=T0_NS + 11 * S) == 0.0  # already synchronised when it began
    samples = _clock_samples(window, "rsu1")
    assert [round((t - T0_NS) / S, 1) for t, _, _ in samples] == [10.5, 11.5, 12.5, 13.5, 13.9]  # one a second, and the last
    assert samples[0][1:] == (350_050_000, 5_000_000)
    assert rsu_status(window[0], "rsu2") is None and rsu_status(None, "rsu1") is None
