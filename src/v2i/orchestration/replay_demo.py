"""A recorded demo re-run: a fresh OBU fed by the replayed RSU traffic, scored like ``v2i demo``.

``v2i demo --record FILE`` (and ``v2i chaos run --record FILE``) record both sides of the link
while the demo runs (``v2i.orchestration.demo_recording``): the RSU side (``rsu``: what the RSU published, and the
recorder's time exchanges with it), the vehicle side (``vehicle``: what reached the OBU after
the link, and the OBU's outputs) and the emulator's control side (``link``: its JSON stats), with the run's spec, start and duration as MCAP metadata
``run``. ``v2i replay FILE --score`` (``ReplayDemo``) starts only an OBU with that spec (``--await-start``),
and once it is ready and watched, gives it a new time zero and replays the vehicle side's RSU traffic into it (``v2i.telemetry.replayer.Replayer``: every stamp
moved to the new start, the RSU clock answered from the recorded exchanges) and scores its
output with the demo's machinery (``InboxScoring``, ``build_report``): the same report keys,
``driver: replay``, plus ``replay`` (what was republished, how late) and ``recording``.

A signed recording (the demo's default, ``--security strict``) is replayed unsigned (a shifted
stamp cannot keep its signature: ``v2i.replay``), so the fresh OBU runs without a PKI (the
report's ``security`` is None) and ``replay.recorded_security`` says what the recorded run did.
"""

from __future__ import annotations

import dataclasses
import threading
import time

from v2i.core.jit import load_kernels
from v2i.offline.kernels import RUN_KERNEL_MODULES
from schemas.codec import CodecError, decode
from schemas.messages import RsuMetrics
from v2i.runtime.transport import open_session

from v2i.orchestration.children import READY_TIMEOUT_S, START_LEAD_S, DemoError, start_all
from v2i.orchestration.demo import Demo
from v2i.orchestration.inbox_scoring import obu_own_count, startup_summary
from v2i.offline.recorded_run import run_of
from v2i.offline.spec import build_report


class ReplayDemo(Demo):
    """Only the OBU runs; the recording's vehicle-side RSU traffic is replayed into it."""

    def __init__(self, recording_path: str, ready_timeout_s: float = READY_TIMEOUT_S, keys_pattern: str = "v2x/rsu/**",
                 progress: str | None = None, given: dict | None = None):
        """``given``: the run's values from the command line (``recorded_run.run_of``: needed for a
        ``v2i record`` file, which carries no run metadata)."""
        from v2i.telemetry.mcap_reader import Recording
        from v2i.telemetry.replayer import Replayer

        self.recording = Recording(recording_path)
        spec, recorded_start_ns = run_of(self.recording, given or {})
        self.recorded_security = spec.security
        super().__init__(dataclasses.replace(spec, security=None), ready_timeout_s=ready_timeout_s,  # replayed unsigned
                         progress=progress)
        self.replayer = Replayer(self.recording, "vehicle" if "vehicle" in self.recording.sides else None, keys_pattern,
                                 recorded_start_ns=recorded_start_ns)

    def run(self) -> dict:
        """Start the OBU, wait until it is ready, subscribe and declare the replayed RSU clocks, then
        give it time zero (aligned to a whole ms of shift) and replay from it."""
        # compiled once per machine (v2i.core.jit: tens of seconds) here, not in the child
        load_kernels(RUN_KERNEL_MODULES)
        stop, sessions, entities, player = threading.Event(), [], [], None
        try:
            self.children["obu"] = self._child("obu")
            self._wait_ready()
            sessions, entities = self._subscribe()  # the monitor, on the OBU's outputs
            feed = open_session(connect=[self.obu_ep])  # the replay: where the link's vehicle side was
            sessions.append(feed)
            start_ns = self.replayer.align(time.time_ns() + round(START_LEAD_S * 1e9))
            entities += self.replayer.declare_clocks(feed)
            self._start_scoring(start_ns)
            self.record.rsu_perception = self._recorded_perception()
            start_all(self.children.values(), start_ns)
            self._started = dict(self.children)
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
            self._end_scoring()
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
        report["obu_output_deadline_misses"] = {self.spec.obu_config().vehicle_id: obu_own_count(self.record)}
        report["startup"] = startup_summary(self.ready_s, self._started.values())
        report["recording"] = str(self.recording.path)
        report["replay"] = {**self.replayer.stats(), "recorded_security": self.recorded_security}
        return report
