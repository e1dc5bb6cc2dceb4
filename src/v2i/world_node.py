"""``v2i world``: the simulated world of a scenario in real time, published as sensor inputs.

For services running ``--source zenoh`` (and for monitors): every RSU camera's detections on
``v2x/sensor/rsu/{rsu_id}/objects``, every vehicle's LiDAR detections and localisation on
``v2x/sensor/vehicle/{vehicle_id}/objects|pose``, and the ground truth on ``v2x/world/truth``
(``v2i.world_feed`` says what and when). Give it the services' ``--start-at-ns``, ``--seed`` and
``--scenario`` and they receive what ``--source sim`` would have sampled.
"""

from __future__ import annotations

import argparse
import threading

from pydantic import Field, field_validator

from v2i.core.jit import load_kernels
from v2i.offline.kernels import RUN_KERNEL_MODULES
from schemas.codec import encode
from v2i.runtime.config import ServiceConfig
from v2i.runtime.process import add_service_options, announce, log, read_start_line, run_service, start_when_told
from v2i.runtime.transport import open_session
from v2i.sim.clock import Clock, SystemClock
from v2i.sim.scenario import load_scenario

from v2i.world_feed import WorldFeed

LATE_NS = 50_000_000  # a publication this far behind its time is counted late


def _renames(values: list[str]) -> dict[str, str]:
    """``SCENARIO_ID=NAME`` (or a bare ``NAME`` for a scenario's only RSU / vehicle) as a map."""
    out = {}
    for value in values:
        scenario_id, _, name = value.rpartition("=")
        out[scenario_id] = name
    return out


class WorldConfig(ServiceConfig):
    listen: list[str] = Field(default_factory=list)
    rsu_id: list[str] = Field(default_factory=list, description="publish a scenario RSU under another id: "
                              "SCENARIO_ID=RSU_ID, or RSU_ID alone for the scenario's only RSU")
    vehicle_id: list[str] = Field(default_factory=list, description="publish a scenario vehicle under another "
                                  "id: NAME=VEHICLE_ID, or VEHICLE_ID alone for the scenario's only vehicle")
    lidar_delay_ms: float = Field(50.0, ge=0, le=10_000, description="vehicle LiDAR capture -> detections "
                                  "published (the OBU's fuse_delay_ms with --source sim)")
    truth_rate_hz: float = Field(10.0, gt=0, le=100)

    @field_validator("rsu_id", "vehicle_id")
    @classmethod
    def _one_name_each(cls, v: list[str]) -> list[str]:
        if len(_renames(v)) != len(v):
            raise ValueError(f"renames the same one twice: {v}")
        return v


class WorldNode:
    def __init__(self, config: WorldConfig, clock: Clock | None = None):
        """The scenario and the feed load here (its renames checked); with ``config.await_start`` the
        feed is built again from time zero after the ready line (``_begin``, ~1 ms)."""
        # the sensors' compiled line of sight (~0.2 s), before the start time: not in the first frame
        load_kernels(RUN_KERNEL_MODULES)
        self.config, self.clock = config, clock or SystemClock()
        self.scenario = load_scenario(config.scenario)
        self.duration_s = config.duration_s or self.scenario.duration_s
        self.start_ns: int | None = None  # time zero (true clock), from _begin
        self.feed = self._feed(config.start_at_ns or self.clock.now_ns())
        self.published = self.late = 0
        if not config.await_start:
            self.start_ns = self.feed.start_ns

    def _feed(self, start_ns: int) -> WorldFeed:
        c = self.config
        return WorldFeed(self.scenario, c.seed, start_ns, self.duration_s, _renames(c.rsu_id), _renames(c.vehicle_id),
                         c.lidar_delay_ms, c.truth_rate_hz)

    def _begin(self, start_ns: int) -> None:
        """Time zero (true clock): every sensor of the feed samples from it."""
        self.start_ns, self.feed = start_ns, self._feed(start_ns)

    def run(self, stop: threading.Event, await_start=read_start_line) -> None:
        """Say ready, (``await_start``: wait for time zero, ``v2i.runtime.process.start_when_told``), then
        publish every sensor input at its time until the run's end or ``stop``."""
        session = open_session(self.config.listen, self.config.connect)
        publishers: dict[str, object] = {}
        try:
            announce("ready", "world", rsus=sorted(self.feed.cameras), vehicles=sorted(self.feed.vehicles),
                     listen=self.config.listen)
            if self.start_ns is None and not start_when_told("world", stop, self._begin, self.clock.now_ns,
                                                             await_start):
                return
            for pub in self.feed.publications():
                if not self._sleep_until(pub.t_ns, stop):
                    return
                if pub.key not in publishers:
                    publishers[pub.key] = session.declare_publisher(pub.key)
                publishers[pub.key].put(encode(pub.message))
                self.published += 1
                self.late += self.clock.now_ns() - pub.t_ns > LATE_NS
        finally:
            for publisher in publishers.values():
                publisher.undeclare()
            session.close()
            log("world", f"stopped: {self.published} messages published ({self.late} over "
                         f"{LATE_NS // 1_000_000} ms late), {self.feed.counts}")

    def _sleep_until(self, t_ns: int, stop: threading.Event) -> bool:
        while not stop.is_set():
            remaining_s = (t_ns - self.clock.now_ns()) * 1e-9
            if remaining_s <= 0:
                return True
            stop.wait(remaining_s)
        return False


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.description = (
        "Simulated world: runs the scenario in real time from --start-at-ns and publishes what the "
        "sensors see, for services running --source zenoh: each RSU camera's detections on "
        "v2x/sensor/rsu/{id}/objects, each vehicle's LiDAR detections and localisation on "
        "v2x/sensor/vehicle/{id}/objects|pose, the ground truth on v2x/world/truth. The same --seed "
        "gives the detections --source sim samples."
    )
    add_service_options(p, "WorldConfig", "tcp/127.0.0.1:7450", "sensor noise")
    p.add_argument("--connect", action="append", metavar="EP", help="Zenoh endpoint to connect to (repeatable)")
    p.add_argument("--rsu-id", action="append", metavar="[SCENARIO_ID=]ID",
                   help="publish a scenario RSU under the id its service runs with (repeatable); a bare ID "
                        "names the scenario's only RSU")
    p.add_argument("--vehicle-id", action="append", metavar="[NAME=]ID",
                   help="publish a scenario vehicle under the id its OBU runs with (repeatable)")
    p.add_argument("--lidar-delay-ms", type=float, help="LiDAR capture -> detections published (default 50)")
    p.add_argument("--truth-rate-hz", type=float, help="ground truth messages per second (default 10)")


def run(args: argparse.Namespace) -> int:
    return run_service("world", WorldConfig, args, WorldNode)
