"""The live RSU's simulated clock is the demo's truth: the clock a ``v2i rsu`` child builds from the
command line the demo gives it (``v2i.services``' clock model over its true clock, from the run's time
zero) reads what the report's truth (``v2i.offline.spec``: ``rsu_clock(spec.rsu_config(), ...)`` from
the same time zero) says, at every instant, across a step too. So a live clock error is the estimate's,
not a scoring mismatch (docs/clock-sync.md, "Live against offline")."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from rsu_service.config import RsuConfig
from v2i.cli import build_parser
from v2i.offline.spec import RunSpec
from v2i.orchestration.demo import Demo
from v2i.orchestration.site_demo import SiteDemo
from v2i.runtime.config import load_config
from v2i.services import _rsu_clock_model
from v2i.sim.clock import SimClock, rsu_clock

START_NS = 1_700_000_000_000_000_000
SPECS = [
    RunSpec(),  # the default: the host's clock itself
    RunSpec(rsu_clock_offset_ms=50.0, rsu_clock_drift_ppm=-85.0),
    RunSpec(rsu_clock_offset_ms=-12.3456789, rsu_clock_drift_ppm=33.3, rsu_clock_step_ms=-700.0,
            rsu_clock_step_at_s=8.0),
]


def demo_argv(spec: RunSpec) -> list[str]:
    """The two-node demo's RSU command line."""
    demo = SimpleNamespace(spec=spec, duration_s=20.0, rsu_ep="tcp/127.0.0.1:7447", pki_dir=Path("pki"),
                           save_wire=None)
    return Demo._service_argv(demo, "rsu")


def site_demo_argv(spec: RunSpec) -> list[str]:
    """A site demo's RSU command line (``two-rsu-corridor``: one per RSU, the same clock flags)."""
    site = SimpleNamespace(spec=spec, rsu_eps={"rsu-b": "tcp/127.0.0.1:7448"}, pki_dir=Path("pki"), save_wire=None,
                           _common=lambda: ["--scenario", spec.scenario, "--seed", str(spec.seed), "--await-start"])
    return SiteDemo._rsu_argv(site, "rsu-b")


def child_config(argv: list[str]) -> RsuConfig:
    """The RsuConfig ``v2i rsu`` makes of ``argv`` (``v2i.runtime.process.run_service``)."""
    assert argv[1:4] == ["-m", "v2i", "rsu"]
    args = build_parser().parse_args(argv[3:])
    return load_config(RsuConfig, None, {f: getattr(args, f) for f in RsuConfig.model_fields if hasattr(args, f)})


@pytest.mark.parametrize("argv_of", [demo_argv, site_demo_argv])
@pytest.mark.parametrize("spec", SPECS)
def test_the_live_rsu_clock_reads_the_reports_truth(argv_of, spec):
    base = SimClock(START_NS)
    live = _rsu_clock_model(child_config(argv_of(spec)))(base, START_NS)
    truth = rsu_clock(spec.rsu_config(), SimClock(), START_NS)
    for t_s in (0.0, 0.1, 5.0, 7.999, 8.0, 8.001, 19.5):
        base.t_ns = START_NS + round(t_s * 1e9)
        assert live.now_ns() == truth.local_from_true(base.t_ns), t_s


def test_a_wrong_flag_would_show():
    """The check above can fail: a drift lost on the way is a truth off by drift * time."""
    spec = SPECS[1]
    config = child_config(demo_argv(spec)).model_copy(update={"clock_drift_ppm": 0.0})
    base = SimClock(START_NS + 10 * 10**9)
    live = _rsu_clock_model(config)(base, START_NS)
    assert live.now_ns() - rsu_clock(spec.rsu_config(), SimClock(), START_NS).local_from_true(base.t_ns) == 850_000
