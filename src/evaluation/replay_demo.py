"""A recorded demo re-run: a fresh OBU fed by the replayed RSU traffic, scored like ``v2i demo``.

``v2i demo --record FILE`` (and ``v2i chaos run --record FILE``) record both sides of the link
while the demo runs (``demo_recorder``): the RSU side (``rsu``: what the RSU published, and the
recorder's time exchanges with it), the vehicle side (``vehicle``: what reached the OBU after
the link, and the OBU's outputs) and the emulator's control side (``link``: its JSON stats), with the run's spec, start and duration as MCAP metadata
``run``. ``v2i replay FILE --score`` (``ReplayDemo``) starts only an OBU with that spec at a new
start time, replays the vehicle side's RSU traffic into it (``v2i.replay.Replayer``: every stamp
moved to the new start, the RSU clock answered from the recorded exchanges) and scores its
output with the demo's machinery (``InboxScoring``, ``build_report``): the same report keys,
``driver: replay``, plus ``replay`` (what was republished, how late) and ``recording``.

A signed recording (the demo's default, ``--security strict``) is replayed unsigned (a shifted
stamp cannot keep its signature: ``v2i.replay``), so the fresh OBU runs without a PKI (the
report's ``security`` is None) and ``replay.recorded_security`` says what the recorded run did.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time

from fusion.jit import load_kernels
from obu_service.source import SimulatedVehicle
from schemas import keys
from schemas.codec import CodecError, decode
from schemas.messages import RsuMetrics
from schemas.transport import open_session

from .demo import Child, Demo, DemoError
from .spec import RunRecord, RunSpec, build_report

RUN_METADATA = "run"


def run_metadata(spec: RunSpec, start_ns: int, duration_s: float, vehicle_id: str, rsu_id: str) -> dict[str, str]:
    """The MCAP metadata record that makes a recording replayable (strings only)."""
    return {"spec": json.dumps(dataclasses.asdict(spec)), "start_ns": str(start_ns), "duration_s": repr(duration_s),
            "vehicle_id": vehicle_id, "rsu_id": rsu_id}


def spec_of(metadata: dict[str, str]) -> RunSpec:
    """The recorded run's spec, its duration made explicit; ValueError when the recording has none."""
    if "spec" not in metadata:
        raise ValueError("the recording has no run metadata (record a run with v2i demo --record)")
    fields = json.loads(metadata["spec"])
    known = {f.name for f in dataclasses.fields(RunSpec)}
    spec = RunSpec(**{k: v for k, v in fields.items() if k in known})
    return dataclasses.replace(spec, duration_s=float(metadata["duration_s"]))


def demo_recorder(demo: Demo, start_ns: int, path: str):
    """A started ``v2i.record.Recorder`` on both sides of ``demo``'s link (time exchanges on the RSU side)."""
    from v2i.record import Recorder

    spec = demo.spec
    meta = run_metadata(spec, start_ns, demo.duration_s, spec.obu_config().vehicle_id, spec.rsu_config().rsu_id)
    sides = [("rsu", demo.rsu_ep), ("vehicle", demo.obu_ep), ("link", demo.control_ep)]  # link: its stats
    recorder = Recorder(sides, path, time_from="rsu",
                        metadata={RUN_METADATA: meta})
    recorder.start()
    return recorder


class ReplayDemo(Demo):
    """Only the OBU runs; the recording's vehicle-side RSU traffic is replayed into it."""

    def __init__(self, recording_path: str, startup_s: float = 4.0, keys_pattern: str = "v2x/rsu/**"):
        from telemetry.mcap_reader import Recording
        from v2i.replay import Replayer

        self.recording = Recording(recording_path)
        spec = spec_of(self.recording.metadata.get(RUN_METADATA, {}))
        self.recorded_security = spec.security
        super().__init__(dataclasses.replace(spec, security=None), startup_s=startup_s)  # replayed unsigned
        self.replayer = Replayer(self.recording, "vehicle" if "vehicle" in self.recording.sides else None, keys_pattern)

    def run(self) -> dict:
        load_kernels()  # compiled once per machine (fusion.jit: tens of seconds) here, before the start time, not in the child
        start_ns = self.replayer.align(time.time_ns() + round(self.startup_s * 1e9))
        cycles = SimulatedVehicle(self.world, self.spec.seed, start_ns).cycle_times_ns(self.duration_s)
        self.record = RunRecord(self.world, start_ns, self.duration_s, cycles)
        self.record.rsu_perception = self._recorded_perception()
        scorer = threading.Thread(target=self._score_inbox, name="replay-scorer", daemon=True)
        scorer.start()
        stop, sessions, entities, player = threading.Event(), [], [], None
        try:
            self.children["obu"] = Child("obu", self._argv("obu", start_ns))
            self.children["obu"].wait_ready(time.monotonic() + (start_ns - time.time_ns()) * 1e-9)
            monitor = open_session(connect=[self.obu_ep])
            feed = open_session(connect=[self.obu_ep])  # the replay: where the link's vehicle side was
            sessions += [monitor, feed]
            vid = self.spec.obu_config().vehicle_id
            entities += [monitor.declare_subscriber(keys.obu_objects(vid), lambda s: self._keep("objects", s)),
                         monitor.declare_subscriber(keys.obu_metrics(vid), lambda s: self._keep("metrics", s)),
                         monitor.declare_subscriber(keys.obu_planning(vid), lambda s: self._keep("planning", s)),
                         *self.replayer.declare_clocks(feed)]
            if not list(monitor.info.peers_zid()):
                raise DemoError(f"cannot connect to the OBU at {self.obu_ep}")
            player = threading.Thread(target=self.replayer.play, args=(feed, stop), name="replay-play", daemon=True)
            player.start()
            self._supervise(start_ns)
        finally:
            stop.set()
            if player is not None:
                player.join()
            for child in self.children.values():
                child.stop()
            for entity in entities:
                entity.undeclare()
            for session in sessions:
                session.close()
            self._tmp.cleanup()
            self._inbox.put(None)
            scorer.join()
        if self._scoring_error is not None:
            raise DemoError(f"scoring the OBU output failed: {self._scoring_error!r}") from self._scoring_error
        return self._report()

    def _recorded_perception(self) -> dict | None:
        """The RSU's own perception scores from its last recorded metrics (RSU side), if any."""
        last = None
        for sample in self.recording.samples("rsu", "v2x/rsu/*/metrics") if "rsu" in self.recording.sides else ():
            try:
                perception = decode(sample.payload, RsuMetrics).perception
            except CodecError:
                continue
            last = perception.model_dump() if perception is not None else last
        return last

    def _report(self) -> dict:
        report = build_report(self.spec, self.world, self.record, driver="replay")
        report["monitor_messages_dropped"] = dict(self.dropped)
        report["recording"] = str(self.recording.path)
        report["replay"] = {**self.replayer.stats(), "recorded_security": self.recorded_security}
        return report
