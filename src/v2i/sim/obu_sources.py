"""The vehicle's simulated own sensing (``obu_service.source.OwnSensing``, ``--source sim``): its
LiDAR detections and localisation sampling the simulated world at the LiDAR's rate."""

from __future__ import annotations

import numpy as np

from obu_service.source import OwnFrame
from v2i.core.clock import frame_times
from v2i.sim.seeding import stream
from v2i.sim.sensors import Lidar, Localization
from v2i.sim.world import World


class SimulatedVehicle:
    """Ego LiDAR (10 Hz) and localisation sampling the simulated world, seen from the vehicle
    ``world`` is the view of (``World(scenario, ego=name)``); the k-th vehicle of a scenario
    draws from the k-th streams."""

    def __init__(self, world: World, seed: int, start_ns: int):
        self.world = world
        self.start_ns = start_ns
        spec = world.scenario.vehicle(world.ego_name)
        index = world.scenario.vehicles.index(spec)
        self.rate_hz = spec.lidar.rate_hz
        self.lidar = Lidar(spec.lidar, stream(seed, "lidar", index))
        self.localization = Localization(spec.localization, stream(seed, "localization", index))

    def cycle_times_ns(self, duration_s: float) -> np.ndarray:
        """(K,) int64 LiDAR capture times: the OBU's 10 Hz cycles."""
        t_s = frame_times(self.rate_hz, duration_s)
        return self.start_ns + np.round(t_s * 1e9).astype(np.int64)

    def capture(self, capture_ns: int) -> OwnFrame:
        t_s = (capture_ns - self.start_ns) * 1e-9
        return OwnFrame(int(capture_ns), self.localization.measure(self.world, t_s), self.lidar.detect(self.world, t_s))
