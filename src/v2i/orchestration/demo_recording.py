"""``v2i demo --record FILE`` (and ``v2i chaos run --record FILE``): both sides of a live demo's link
recorded while it runs, with the run's spec, start and duration as MCAP metadata ``run``, for
``v2i replay FILE --score`` (``v2i.orchestration.replay_demo``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from v2i.offline.recorded_run import RUN_METADATA, run_metadata

if TYPE_CHECKING:
    from v2i.orchestration.demo import Demo


def demo_recorder(demo: Demo, start_ns: int, path: str):
    """A started ``v2i.telemetry.recorder.Recorder`` on both sides of ``demo``'s link (time exchanges on the RSU side)."""
    from v2i.telemetry.recorder import Recorder

    spec = demo.spec
    meta = run_metadata(spec, start_ns, demo.duration_s, spec.obu_config().vehicle_id, spec.rsu_config().rsu_id)
    sides = [("rsu", demo.rsu_ep), ("vehicle", demo.obu_ep), ("link", demo.control_ep)]  # link: its stats
    recorder = Recorder(sides, path, time_from="rsu",
                        metadata={RUN_METADATA: meta})
    recorder.start()
    return recorder
