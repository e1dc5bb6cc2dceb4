"""``v2i attack`` waits for the site with one bound (``--ready-timeout``) and says what it awaits."""

from __future__ import annotations

import argparse
import time

import pytest

from v2i.adversary.attack_live import AttackRun, NotReady
from v2i.cli import main


def test_a_site_that_never_shows_its_traffic_is_named_after_the_ready_timeout(capsys):
    args = argparse.Namespace(seed=0, rsu_id="rsu1", vehicle_id="ego", link_id="link1", ready_timeout=0.5)
    run = AttackRun(args, ["unsigned"], attacker=None)  # no sessions: nothing ever arrives
    t0 = time.monotonic()
    with pytest.raises(NotReady) as error:
        run._wait_ready()
    assert 0.5 <= time.monotonic() - t0 < 5.0
    text = str(error.value)
    assert text.startswith("not ready within 0.5 s (--ready-timeout): still waiting for genuine signed lists of the RSU")
    assert "; the ego's pose; OBU metrics with an RSU clock estimate" in text
    assert "v2i attack: waiting for genuine signed lists of the RSU" in capsys.readouterr().err  # the progress line


def test_attack_refuses_a_ready_timeout_that_is_not_positive(capsys):
    code = main(["attack", "--connect", "tcp/127.0.0.1:9", "--sniff", "tcp/127.0.0.1:9", "--pki", "/nonexistent",
                 "--kinds", "unsigned", "--ready-timeout", "0"])
    assert code == 2 and "--ready-timeout > 0" in capsys.readouterr().err
