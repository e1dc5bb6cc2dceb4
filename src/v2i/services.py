"""The services composed: the composition root of ``v2i rsu`` and ``v2i obu``.

A configuration names a site file (``--site``) or a scenario (``--scenario``, which contains its
site: ``v2i.sim.scenario_site``). This module picks what the nodes are handed: the ``Site``, the
RSU's camera source (the simulator's for ``--source sim|camera``, a recording for ``--source
video``, none for ``--source zenoh``), the RSU's clock model (the simulator's offset, drifting and
stepping clock when the ``clock_*`` fields ask for one), the OBU's own sensing (the simulator's
LiDAR and localisation for ``--source sim``) or ego camera (``--fusion roif``), and a scenario's
duration as the run's default. The services never import the simulator; this module does, and
only for a configuration that needs it: ``--site FILE --source zenoh`` loads no scenario and no
part of ``v2i.sim``.

Imports are deferred to the functions, so that ``v2i rsu --help`` loads none of this.
"""

from __future__ import annotations

import argparse
from functools import partial
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from obu_service.config import ObuConfig
    from rsu_service.config import RsuConfig
    from v2i.core.clock import Clock, ClockModel
    from v2i.runtime.site import Site
    from v2i.sim.scenario import Scenario


def run_rsu(args: argparse.Namespace) -> int:
    """``v2i rsu``."""
    from rsu_service import cli

    return cli.run(args, rsu_node)


def run_obu(args: argparse.Namespace) -> int:
    """``v2i obu``."""
    from obu_service import cli

    return cli.run(args, obu_node)


def rsu_node(config: RsuConfig, true_clock: Clock | None = None):
    """The ``rsu_service.node.RsuNode`` that ``config`` describes, its source loaded (a renderer and
    detector take seconds) and started at ``config.start_at_ns`` or now (``true_clock``)."""
    _pki_first(config.pki_dir, signer=config.identity or config.rsu_id)  # before the node's imports (~0.3 s)
    site = _site_first(config.site)
    from rsu_service.node import RsuNode
    from v2i.core.clock import SystemClock

    true_clock = true_clock or SystemClock()
    start_ns = config.start_at_ns or true_clock.now_ns()
    if site is not None:
        from rsu_service.source import video_source

        source = video_source(config, site, start_ns) if config.source == "video" else None
        return RsuNode(config, site, source, _rsu_clock_model(config), true_clock)
    import rsu_service
    from v2i import sim
    from v2i.core.jit import load_kernels
    from v2i.sim.rsu_sources import make_source
    from v2i.sim.world import World

    # the compiled loops, the simulator's too (~0.3 s), before a source is built, as the node's
    load_kernels((*rsu_service.KERNEL_MODULES, *sim.KERNEL_MODULES))
    scenario, site = _scenario_and_site(config.scenario)
    config = _for_scenario(config, scenario)
    # a camera sees every vehicle of the site (World(site=True))
    source = None if config.source == "zenoh" else make_source(config, World(scenario, site=True), start_ns)
    return RsuNode(config, site, source, _rsu_clock_model(config), true_clock)


def obu_node(config: ObuConfig, clock: Clock | None = None):
    """The OBU node that ``config`` describes: ``obu_service.node.ObuNode`` (object-level fusion) or
    ``obu_service.image_fusion_node.ImageFusionNode`` (``fusion roif``, its camera loaded and started
    at ``config.start_at_ns`` or now)."""
    from v2i.core.clock import SystemClock

    _pki_first(config.pki_dir)
    clock = clock or SystemClock()
    if config.fusion == "roif" and config.source != "sim":
        raise ValueError("--source zenoh feeds object-level fusion; --fusion roif renders its own camera")
    if config.site is not None:
        site = _site_first(config.site)
        from obu_service.node import ObuNode

        return ObuNode(config, site, None, clock)
    from v2i.sim.world import World

    scenario, site = obu_scenario_site(config)
    config = _for_scenario(config, scenario)
    if config.fusion == "roif":
        from obu_service.image_fusion_node import ImageFusionNode
        from v2i.sim.ego_camera import EgoCamera

        camera = EgoCamera(World(scenario), config.seed, config.start_at_ns or clock.now_ns(), config.roif_model,
                           threads=config.roif_threads)
        return ImageFusionNode(config, site, camera, clock)
    import obu_service
    from obu_service.node import ObuNode
    from v2i import sim
    from v2i.core.jit import load_kernels
    from v2i.sim.obu_sources import SimulatedVehicle

    # the compiled loops, the simulator's too (~0.3 s), before the world is built, as the node's
    load_kernels((*obu_service.KERNEL_MODULES, *sim.KERNEL_MODULES))
    sensing = None
    if config.source == "sim":
        # this vehicle's view when the scenario has it (its LiDAR, its streams), else the ego's
        own = config.vehicle_id if config.vehicle_id in [v.name for v in scenario.vehicles] else None
        sensing = partial(SimulatedVehicle, World(scenario, ego=own), config.seed)
    return ObuNode(config, site, sensing, clock)


def _pki_first(pki_dir: str | None, signer: str | None = None) -> None:
    """Read the PKI files a service is about to load (its trust, or ``signer``'s key and certificate)
    before the slow part of its start-up (compiled kernels, a simulated world, a detector: 1-3 s), so
    that a bad one (``/dev/zero``, a FIFO, a corrupt certificate) is refused at once; ValueError naming
    the file. The node reads them again as it is built (a few small files, ~1 ms)."""
    if pki_dir is None:
        return
    from v2i.security.pki import PkiError, load_signer, load_trust

    try:
        load_signer(pki_dir, signer) if signer is not None else load_trust(pki_dir)
    except PkiError as exc:
        raise ValueError(str(exc)) from None


def _site_first(path: str | None) -> Site | None:
    """The site file at ``path`` (None without one), read before the node's imports (~0.3 s)."""
    if path is None:
        return None
    from v2i.runtime.site import load_site

    return load_site(path)


def obu_scenario_site(config: ObuConfig) -> tuple[Scenario, Site]:
    """The scenario ``config`` names and its site; ValueError, saying where a map would be found,
    when the ``lane`` compensation needs a map the scenario has not."""
    scenario, site = _scenario_and_site(config.scenario)
    if config.compensation == "lane" and site.map is None:
        from v2i.sim.maps import missing_map

        raise ValueError(missing_map(config.scenario, "compensation 'lane'"))
    return scenario, site


def _scenario_and_site(name_or_path: str) -> tuple[Scenario, Site]:
    """A bundled scenario by name or a scenario YAML by path, and the site it contains."""
    from v2i.sim.maps import scenario_map
    from v2i.sim.scenario import load_scenario
    from v2i.sim.scenario_site import site_of

    scenario = load_scenario(name_or_path)
    return scenario, site_of(scenario, scenario_map(name_or_path))


def _for_scenario(config, scenario: Scenario):
    """``config`` with the scenario's duration when it sets none."""
    return config if config.duration_s is not None else config.model_copy(update={"duration_s": scenario.duration_s})


def _rsu_clock_model(config: RsuConfig) -> ClockModel:
    """The RSU's own clock: the simulator's offset, drifting, stepping one when the config's clock_*
    fields ask for it (``v2i.sim.clock.rsu_clock``), else the true clock itself."""
    if not config.skewed_clock:
        from v2i.core.clock import UnskewedClock

        return UnskewedClock.of
    from v2i.sim.clock import rsu_clock

    return partial(rsu_clock, config)
