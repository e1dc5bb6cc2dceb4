"""What ``v2i world`` publishes, and when (pure: no Zenoh, no clock; times are true-clock ns).

The simulated world of a scenario, sampled by the very sensor models the services embed with
``--source sim``: each RSU's camera (``v2i.sim.rsu_sources.SimulatedCamera``, site view) and
each vehicle's LiDAR and localisation (``v2i.sim.obu_sources.SimulatedVehicle``, the vehicle's
own view), with the same seeded streams, so a service fed by ``v2i world`` over ``--source
zenoh`` receives the detections it would have sampled itself (quantised by the wire).

Per sensor frame captured at c (true clock):
- RSU camera: ``SensorObjects`` (map) published at c + the frame's processing delay;
- vehicle: ``LocalizationPose`` at c, ``SensorObjects`` (base_link) at c + ``lidar_delay_ms``
  (the OBU's own perception latency, ``ObuConfig.fuse_delay_ms``);
- ``GroundTruth`` of the site at ``truth_rate_hz``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from functools import partial

import numpy as np

from v2i.core.frames import Pose2D
from v2i.core.objects import ObjectArray
from v2i.core.scheduler import Timeline
from v2i.fusion.wire import fit_to_wire, states_from_objects
from schemas import keys
from schemas.messages import Message
from schemas.sensor_messages import GroundTruth, LocalizationPose, SensorHeader, SensorObjects, VehicleTruth
from v2i.sim.obu_sources import SimulatedVehicle
from v2i.sim.rsu_sources import SimulatedCamera
from v2i.sim.scenario import Scenario
from v2i.sim.sensors import frame_times
from v2i.sim.world import World


@dataclass(frozen=True)
class Publication:
    """One message to put on ``key`` at true time ``t_ns``."""

    t_ns: int
    key: str
    message: Message


def sensor_objects(sensor_id: str, sensor: str, seq: int, frame_id: str, capture_ns: int, ready_ns: int,
                   dets: ObjectArray) -> SensorObjects:
    """The wire message of one sensor frame; detection ids 0..N-1 (the models' ids are -1)."""
    dets, _ = fit_to_wire(dets.with_(ids=np.arange(len(dets), dtype=np.int64)))
    return SensorObjects(header=SensorHeader(sensor_id=sensor_id, sensor=sensor, seq=seq, frame_id=frame_id,
                                             capture_time_ns=capture_ns, ready_time_ns=ready_ns),
                         objects=states_from_objects(dets))


def localization_pose(vehicle_id: str, seq: int, t_ns: int, pose: Pose2D) -> LocalizationPose:
    """The wire message of a pose estimate, with its stated error statistics."""
    unc = pose.uncertainty
    cov = np.zeros((3, 3)) if unc is None else unc.cov
    return LocalizationPose(vehicle_id=vehicle_id, seq=seq, t_ns=t_ns, x=pose.x, y=pose.y, yaw=pose.yaw, vx=pose.vx,
                            vy=pose.vy, cov_xx=cov[0, 0], cov_xy=cov[0, 1], cov_yy=cov[1, 1], cov_xyaw=cov[0, 2],
                            cov_yyaw=cov[1, 2], cov_yawyaw=cov[2, 2],
                            correlation_time_s=0.0 if unc is None else min(unc.correlation_time_s, 1e6))


def _renamed(names: Mapping[str, str], scenario_ids: list[str], what: str) -> dict[str, str]:
    """scenario id -> published id; ``names`` may rename some (a lone "" key: the only one)."""
    if "" in names:
        if len(scenario_ids) != 1:
            raise ValueError(f"a bare --{what}-id NAME needs a scenario with one {what}, this one has "
                             f"{len(scenario_ids)}: use SCENARIO_ID=NAME")
        names = {scenario_ids[0]: names[""]}
    unknown = sorted(set(names) - set(scenario_ids))
    if unknown:
        raise ValueError(f"no {what} {unknown} in the scenario; its {what}s: {scenario_ids}")
    out = {sid: names.get(sid, sid) for sid in scenario_ids}
    for published in out.values():
        keys.check_id(published)
    return out


class WorldFeed:
    """The publications of one run, in time order (``publications``)."""

    def __init__(self, scenario: Scenario, seed: int, start_ns: int, duration_s: float,
                 rsu_ids: Mapping[str, str] | None = None, vehicle_ids: Mapping[str, str] | None = None,
                 lidar_delay_ms: float = 50.0, truth_rate_hz: float = 10.0):
        """``rsu_ids`` / ``vehicle_ids``: publish the scenario's RSU / vehicle under another id."""
        self.scenario, self.start_ns, self.duration_s = scenario, start_ns, duration_s
        self.lidar_delay_ns, self.truth_rate_hz = round(lidar_delay_ms * 1e6), truth_rate_hz
        self.rsu_ids = _renamed(rsu_ids or {}, [r.id for r in scenario.rsus], "rsu")
        self.vehicle_ids = _renamed(vehicle_ids or {}, [v.name for v in scenario.vehicles], "vehicle")
        self.site = World(scenario, site=True)
        self.cameras = {self.rsu_ids[r.id]: SimulatedCamera(self.site, seed, start_ns, r.id) for r in scenario.rsus}
        self.views = {self.vehicle_ids[v.name]: World(scenario, ego=v.name) for v in scenario.vehicles}
        self.vehicles = {vid: SimulatedVehicle(world, seed, start_ns) for vid, world in self.views.items()}
        self.counts: dict[str, int] = {"rsu_objects": 0, "vehicle_objects": 0, "poses": 0, "truths": 0}

    def publications(self) -> Iterator[Publication]:
        """Every publication of the run in non-decreasing ``t_ns``. A sensor is sampled when its
        capture time comes up (each sensor's stream in capture order, as in the services); at one
        time, in the order scheduled (``v2i.core.scheduler.Timeline``)."""
        timeline: Timeline[Publication | Callable[[int], list[Publication]]] = Timeline()
        for rsu_id, camera in self.cameras.items():
            for k, c in enumerate(camera.capture_times_ns(self.duration_s)):
                timeline.push(int(c), partial(self._camera, rsu_id=rsu_id, seq=k))
        for vid, vehicle in self.vehicles.items():
            for k, c in enumerate(vehicle.cycle_times_ns(self.duration_s)):
                timeline.push(int(c), partial(self._vehicle, vid=vid, seq=k))
        for k, t_s in enumerate(frame_times(self.truth_rate_hz, self.duration_s)):
            timeline.push(self.start_ns + round(t_s * 1e9), partial(self._truth, seq=k))
        while timeline:
            t_ns, event = timeline.pop()
            if isinstance(event, Publication):
                yield event
                continue
            for pub in event(t_ns):  # a sensor sampled at t_ns: what it publishes, and when
                timeline.push(pub.t_ns, pub)

    def _camera(self, capture_ns: int, rsu_id: str, seq: int) -> list[Publication]:
        frame = self.cameras[rsu_id].capture(capture_ns)
        self.counts["rsu_objects"] += 1
        msg = sensor_objects(rsu_id, "camera", seq, "map", frame.capture_true_ns, frame.ready_true_ns, frame.detections)
        return [Publication(frame.ready_true_ns, keys.sensor_rsu_objects(rsu_id), msg)]

    def _vehicle(self, capture_ns: int, vid: str, seq: int) -> list[Publication]:
        frame = self.vehicles[vid].capture(capture_ns)
        ready_ns = frame.capture_ns + self.lidar_delay_ns
        self.counts["poses"] += 1
        self.counts["vehicle_objects"] += 1
        return [Publication(frame.capture_ns, keys.sensor_vehicle_pose(vid),
                            localization_pose(vid, seq, frame.capture_ns, frame.pose)),
                Publication(ready_ns, keys.sensor_vehicle_objects(vid),
                            sensor_objects(vid, "lidar", seq, "base_link", frame.capture_ns, ready_ns, frame.detections))]

    def _truth(self, t_ns: int, seq: int) -> list[Publication]:
        self.counts["truths"] += 1
        return [Publication(t_ns, keys.WORLD_TRUTH, self.truth(t_ns, seq))]

    def truth(self, t_ns: int, seq: int = 0) -> GroundTruth:
        """The site at true time ``t_ns``: every actor present (and every vehicle as an actor,
        ids as ``v2i.sim.world``) and each vehicle's true pose and size."""
        t_s = (t_ns - self.start_ns) * 1e-9
        actors, _ = fit_to_wire(self.site.actors_at(t_s))
        vehicles = []
        for vid, world in self.views.items():
            pose, (length, width, height) = world.ego_at(t_s), world.ego_size
            vehicles.append(VehicleTruth(vehicle_id=vid, x=pose.x, y=pose.y, yaw=pose.yaw, vx=pose.vx, vy=pose.vy,
                                         length=length, width=width, height=height))
        return GroundTruth(seq=seq, t_ns=t_ns, scenario=self.scenario.name[:128], objects=states_from_objects(actors),
                           vehicles=tuple(vehicles))
