"""The vehicle-only baseline: the vehicle's own sensors alone, through a fixed own-only tracker.

A baseline must not depend on what it is compared with. The fused output's own-source objects
do (they move with the link: what the RSU data merged into them, which mode ran), so the
baseline is a second OBU pipeline of its own: the same own frames the OBU gets (LiDAR objects
and pose, ``v2i.sim.obu_sources.SimulatedVehicle``), every cycle, through the KF tracker the
``kf`` method uses with no RSU and no V2V input (``kf-vehicle``, ``predict``), its output
published at the cycle time and scored by its own ``TargetTally``. It is a function of the
scenario, the seed, the start time and the cycle times alone: the same for every ``--fusion``,
``--fusion-mode``, link profile, chaos timeline and security policy.

``OwnBaseline.add`` takes a frame the run already captured (``v2i eval``: the OBU's own, no
second sensing); ``own_baseline`` recomputes it from those four (``v2i demo``, whose own frames
are sampled in the OBU process by the same ``SimulatedVehicle``).
"""

from __future__ import annotations

from collections.abc import Sequence

from obu_service.config import ObuConfig
from obu_service.pipeline import ObuPipeline
from obu_service.source import OwnFrame
from v2i.core.objects import ObjectArray
from v2i.scoring.metrics import CycleFrame, TargetTally
from v2i.sim.obu_sources import SimulatedVehicle
from v2i.sim.scenario_site import site_of
from v2i.sim.world import World

BASELINE_FUSION = "kf-vehicle"  # the kf method's tracker, own objects only
BASELINE_COMPENSATION = "predict"


class OwnBaseline:
    """The own-only tracker of one vehicle (``world``'s ego) and the target's tally of its output."""

    def __init__(self, world: World, start_ns: int, site=None):
        """``site``: the scenario's ``Site`` (``site_of``; built when None)."""
        site = site or site_of(world.scenario)  # its RSUs and vehicle sizes (no map: no lane compensation)
        config = ObuConfig(vehicle_id=world.ego_name, fusion=BASELINE_FUSION, compensation=BASELINE_COMPENSATION,
                           scenario=world.scenario.name)
        self.world, self.start_ns = world, start_ns
        self.obu = ObuPipeline(config.pipeline_config(site), config.lanes(site))
        self.tally = TargetTally(world.target_id)

    def add(self, frame: OwnFrame, truth: tuple[float, ObjectArray] | None = None) -> None:
        """One own frame: a cycle at its capture time, fused at once (no RSU to wait for) and scored;
        ``truth``: (t_s, the truth in base_link) of that capture (``Lidar.last_truth``), else derived."""
        self.obu.on_pose(frame.capture_ns, frame.pose)
        self.obu.on_detections(frame.detections, frame.capture_ns)
        out = self.obu.fuse(frame.capture_ns)
        self.tally.add(CycleFrame.of(self.world, out, self.start_ns, truth))


def own_baseline(world: World, seed: int, start_ns: int, cycle_times_ns: Sequence[int], site=None) -> TargetTally:
    """The baseline's tally from scratch: a fresh ``SimulatedVehicle`` (scenario, seed, start) sampled at
    the cycle times in order, as the OBU's own sensing samples them; identical to ``OwnBaseline.add`` fed
    with a run's own frames."""
    sensing, baseline = SimulatedVehicle(world, seed, start_ns), OwnBaseline(world, start_ns, site)
    for t_ns in cycle_times_ns:
        baseline.add(sensing.capture(int(t_ns)), sensing.lidar.last_truth)
    return baseline.tally
