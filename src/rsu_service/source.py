"""Perception sources of the RSU. The default is the scenario's simulated camera."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fusion.objects import ObjectArray
from sim.seeding import stream
from sim.sensors import RsuCamera, frame_times
from sim.world import World


@dataclass(frozen=True)
class Frame:
    """One processed camera frame: detections (map frame) and its true-clock times."""

    capture_true_ns: int
    ready_true_ns: int  # capture + processing delay: when the detections exist
    detections: ObjectArray


class SimulatedCamera:
    """Camera + detector of the scenario's RSU, sampling the simulated world.

    Frame k is captured at start + k / rate (true clock); its detections are ready after
    the detector's processing delay (80-120 ms by default, seed 001).
    """

    def __init__(self, world: World, seed: int, start_ns: int):
        self.world = world
        self.start_ns = start_ns
        self.camera = RsuCamera(world.scenario.rsu, stream(seed, "rsu_camera"))

    @property
    def upsample_offset_ns(self) -> int:
        """Half a frame period: when the upsampled (second) list of a frame is published."""
        return round(0.5e9 / self.world.scenario.rsu.rate_hz)

    def capture_times_ns(self, duration_s: float) -> np.ndarray:
        """(K,) int64 true capture times within the run."""
        t_s = frame_times(self.world.scenario.rsu.rate_hz, duration_s)
        return self.start_ns + np.round(t_s * 1e9).astype(np.int64)

    def capture(self, capture_true_ns: int) -> Frame:
        dets, delay_s = self.camera.detect(self.world, (capture_true_ns - self.start_ns) * 1e-9)
        return Frame(int(capture_true_ns), int(capture_true_ns + round(delay_s * 1e9)), dets)
