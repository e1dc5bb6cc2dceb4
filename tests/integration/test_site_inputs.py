"""A site, not a scenario: ``v2i rsu`` and ``v2i obu`` on ``examples/site.yaml`` with ``--source
zenoh`` (no ``--scenario``, no ``--duration``: they run until stopped), fed by
``examples/external_publisher.py`` (the roadside camera and the vehicle), fuse the publisher's car
from both. Real processes on explicit tcp/127.0.0.1 endpoints, deadlines rather than sleeps, every
session closed and every process stopped."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from v2i.orchestration.children import READY_TIMEOUT_S, Child, start_all, wait_ready
from schemas import keys
from schemas.messages import SOURCE_RSU, SOURCE_VEHICLE, FusedObjectList, ObuMetrics
from v2i.runtime.transport import free_tcp_endpoint

from test_open_inputs import EXAMPLE, V2I, Probe, collect  # tests/integration is on sys.path (rootdir-less import)

pytestmark = [pytest.mark.integration, pytest.mark.timeout(READY_TIMEOUT_S + 90)]

SITE = Path(__file__).resolve().parents[2] / "examples" / "site.yaml"


def test_rsu_and_obu_on_a_site_file_fuse_the_external_publishers_car_from_both():
    rsu_ep, obu_ep = free_tcp_endpoint(), free_tcp_endpoint()
    on_site = ["--site", str(SITE), "--source", "zenoh", "--await-start"]
    children = [Child("rsu", [*V2I, "rsu", *on_site, "--listen", rsu_ep]),
                Child("obu", [*V2I, "obu", *on_site, "--listen", obu_ep, "--connect", rsu_ep])]
    probe = None
    try:
        wait_ready(children)
        probe = Probe(obu_ep, {keys.obu_objects("ego"): FusedObjectList, keys.obu_metrics("ego"): ObuMetrics})
        start_all(children)
        children.append(Child("publisher", [sys.executable, str(EXAMPLE), "--connect", obu_ep,
                                            "--rsu-connect", rsu_ep, "--duration", "40"]))
        outputs, metrics = probe.queues[keys.obu_objects("ego")], probe.queues[keys.obu_metrics("ego")]

        def has_the_car_from_both(out: FusedObjectList) -> bool:
            return any(abs(o.x - 20.0) < 1.0 and abs(o.y - 3.5) < 1.0 and o.sources & SOURCE_VEHICLE
                       and o.sources & SOURCE_RSU for o in out.objects)

        # the publisher prints no ready line: its start-up is given the bound every service gets; then the
        # RSU confirms a track over a few of its 5 Hz frames and the OBU's clock estimate admits its lists
        first = collect(outputs, has_the_car_from_both, READY_TIMEOUT_S)
        later = collect(outputs, lambda o: o.cycle_time_ns > first.cycle_time_ns + 500_000_000, 5.0)
        assert later.publish_time_ns - later.cycle_time_ns < 100_000_000 and later.ego_x > 0.0
        m = collect(metrics, lambda m: m.cycles >= 10 and any(r.messages_accepted for r in m.rsus), 5.0)
        assert [r.rsu_id for r in m.rsus] == ["rsu1"]  # the site's RSU, registered
        assert not {r for r in m.rejected if r.startswith("input_") and r != "input_missing"}
    finally:
        if probe is not None:
            probe.close()
        for child in reversed(children):
            child.stop()
