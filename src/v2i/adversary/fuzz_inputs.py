"""Fuzz targets for the open sensor inputs (``v2i fuzz --target obu-inputs|rsu-inputs``).

- ``obu-inputs``: ``v2i world`` feeding ``v2i obu --source zenoh``; the attacker publishes on the
  OBU's own input keys (``v2x/sensor/vehicle/ego/objects|pose``): every hostile kind of
  ``v2i.adversary.hostile`` built around ``SensorObjects`` and ``LocalizationPose``, plus floods,
  replays of the world's genuine frames, spoofed sensor ids, wrong frames and future stamps.
  Normal output: a fused list per 10 Hz cycle, late after 100 ms.
- ``rsu-inputs``: ``v2i world`` feeding ``v2i rsu --source zenoh``, the attacker on
  ``v2x/sensor/rsu/rsu1/objects``. Normal output: the object lists at the camera rate, late when
  published more than 250 ms after capture.

Without signatures a hostile but valid frame on a node's own key is indistinguishable from its
sensor's: such frames are accepted; what is measured is that nothing crashes or stalls, and
that the refusals are counted (``input_<reason>``).
"""

from __future__ import annotations

import sys
import time
from collections import Counter

from schemas import keys
from schemas.codec import CodecError, decode, encode
from schemas.messages import FusedObjectList, ObjectList, ObuMetrics, RsuMetrics
from schemas.sensor_messages import LocalizationPose, SensorHeader, SensorObjects
from v2i.runtime.transport import free_tcp_endpoint
from schemas.wire_view import pack_view, unpack_view
from v2i.sim.scenario import load_scenario

from v2i.adversary.fuzz import MS, RSU_ID, VEHICLE_ID, FuzzRun
from v2i.adversary.hostile import HostileInputs

RSU_LATE_NS = 250 * MS


class SensorHostileInputs(HostileInputs):
    """``HostileInputs`` that also know the sensor input types (for node ``node_id``, frame ``frame_id``)."""

    def __init__(self, rng, node_id: str, frame_id: str):
        super().__init__(rng, RSU_ID, VEHICLE_ID)
        self.node_id, self.frame_id = node_id, frame_id

    def valid(self, type_name: str, t_ns: int, n_objects: int = 8, **header) -> bytes:
        if type_name == "sensor_objects":
            return encode(self.frame(t_ns, n_objects, **header))
        if type_name == "localization_pose":
            return encode(LocalizationPose(vehicle_id=header.get("sensor_id", self.node_id), t_ns=t_ns,
                                           x=float(self.rng.uniform(-50, 50)), y=float(self.rng.uniform(-50, 50)),
                                           cov_xx=0.01, cov_yy=0.01, cov_yawyaw=1e-4))
        return super().valid(type_name, t_ns, n_objects, **header)

    def frame(self, t_ns: int, n: int = 8, spread_m: float = 80.0, **header) -> SensorObjects:
        fields = {"sensor_id": self.node_id, "seq": int(self.rng.integers(1 << 40)), "frame_id": self.frame_id,
                  "capture_time_ns": t_ns - 60 * MS, "ready_time_ns": t_ns - 10 * MS} | header
        return SensorObjects(header=SensorHeader(**fields), objects=self._objects(n, spread_m))

    def extreme_values(self, type_name: str, t_ns: int) -> bytes:
        if type_name == "sensor_objects":
            return encode(self.frame(t_ns, int(self.rng.choice([1, 256, 1024])), spread_m=1e6))
        return super().extreme_values(type_name, t_ns)

    def absurd_times(self, type_name: str, t_ns: int) -> bytes:
        if type_name != "sensor_objects":
            return super().absurd_times(type_name, t_ns)
        envelope = unpack_view(self.valid(type_name, t_ns))
        field = str(self.rng.choice(["capture_time_ns", "ready_time_ns"]))
        envelope["d"]["header"][field] = int(self.rng.choice([0, -1, t_ns + 10**12, t_ns - 10**12, 2**63 - 1]))
        return pack_view(envelope)


class _InputsFuzz(FuzzRun):
    """The shared driver: ``v2i world`` + the target with ``--source zenoh``; hostile inputs on its keys."""

    node_id, frame_id = "", ""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.hostile = SensorHostileInputs(self.rng, self.node_id, self.frame_id)

    def input_key(self, typ: str) -> str:
        raise NotImplementedError

    def argv(self, duration_s: float) -> dict[str, list[str]]:
        self.eps = {self.name: free_tcp_endpoint()}
        base, common = [sys.executable, "-m", "v2i"], self.common(duration_s)
        service = self.name.removesuffix("-inputs")
        return {self.name: [*base, service, "--source", "zenoh", "--listen", self.eps[self.name], *common],
                "world": [*base, "world", "--connect", self.eps[self.name], "--rsu-id", RSU_ID, *common]}

    def deliver(self, typ: str, payload: bytes) -> None:
        self.attacker.put(self.input_key(typ), payload)

    def special_actions(self) -> list:
        def valid(**header) -> bytes:
            return encode(self.hostile.frame(time.time_ns(), **header))

        flood = valid()
        return [("flood", lambda: self.deliver("sensor_objects", flood)),
                ("spoofed_id", lambda: self.deliver("sensor_objects", valid(sensor_id="intruder"))),
                ("wrong_frame", lambda: self.deliver("sensor_objects", valid(
                    frame_id="map" if self.frame_id == "base_link" else "base_link"))),
                ("future", lambda: self.deliver("sensor_objects", valid(capture_time_ns=time.time_ns() + 5000 * MS,
                                                                        ready_time_ns=time.time_ns() + 5000 * MS))),
                ("replay", self._replay)]

    def _replay(self) -> None:
        with self.lock:
            genuine = self.genuine
        if genuine is not None:
            self.deliver("sensor_objects", genuine)

    def _on_genuine(self, sample) -> None:
        with self.lock:
            self.genuine = sample.payload.to_bytes()

    def _on_metrics_of(self, model):
        def on(sample) -> None:
            try:
                metrics = decode(sample.payload.to_bytes(), model)
            except CodecError:
                return
            with self.lock:
                self.metrics = metrics.model_dump()
        return on

    def refused(self) -> Counter[str]:
        with self.lock:
            return Counter((self.metrics or {}).get("rejected", {}))


class ObuInputsFuzz(_InputsFuzz):
    name, node_id, frame_id = "obu-inputs", VEHICLE_ID, "base_link"
    input_types = ("sensor_objects", "localization_pose")

    def input_key(self, typ: str) -> str:
        return (keys.sensor_vehicle_objects if typ == "sensor_objects" else keys.sensor_vehicle_pose)(VEHICLE_ID)

    def open(self) -> None:
        self.metrics, self.genuine = None, None
        s = self.attacker = self.session(connect=[self.eps[self.name]])
        self.declare(s.declare_subscriber(keys.obu_objects(VEHICLE_ID), self._on_fused))
        self.declare(s.declare_subscriber(keys.obu_metrics(VEHICLE_ID), self._on_metrics_of(ObuMetrics)))
        self.declare(s.declare_subscriber(keys.sensor_vehicle_objects(VEHICLE_ID), self._on_genuine))

    def _on_fused(self, sample) -> None:
        try:
            out = decode(sample.payload.to_bytes(), FusedObjectList)
        except CodecError:
            return
        self.output(out.cycle_time_ns, out.publish_time_ns - out.cycle_time_ns > self.deadline_ns, out.mode)

    def expected_outputs(self, seconds: float) -> int:
        return int(seconds * 10.0)

    def extra(self) -> dict:
        with self.lock:
            metrics = self.metrics or {}
        return {"obu_output_deadline_misses": metrics.get("output_deadline_misses"), "obu_cycles": metrics.get("cycles")}


class RsuInputsFuzz(_InputsFuzz):
    name, node_id, frame_id = "rsu-inputs", RSU_ID, "map"
    input_types = ("sensor_objects",)

    def input_key(self, typ: str) -> str:
        return keys.sensor_rsu_objects(RSU_ID)

    def open(self) -> None:
        self.metrics, self.genuine = None, None
        s = self.attacker = self.session(connect=[self.eps[self.name]])
        self.declare(s.declare_subscriber(keys.rsu_objects(RSU_ID), self._on_list))
        self.declare(s.declare_subscriber(keys.rsu_metrics(RSU_ID), self._on_metrics_of(RsuMetrics)))
        self.declare(s.declare_subscriber(keys.sensor_rsu_objects(RSU_ID), self._on_genuine))

    def _on_list(self, sample) -> None:
        try:
            header = decode(sample.payload.to_bytes(), ObjectList).header
        except CodecError:
            return
        self.output(time.time_ns(), header.publish_time_ns - header.capture_time_ns > RSU_LATE_NS)

    def expected_outputs(self, seconds: float) -> int:
        return int(seconds * load_scenario("red-light-runner").rsu.rate_hz)

