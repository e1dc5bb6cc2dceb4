"""Which run a recording is of: the spec and scenario start that ``v2i replay --score`` needs.

``v2i demo --record`` (``v2i.orchestration.demo_recording.demo_recorder``) writes them into the file as
the MCAP metadata record ``run`` (``run_metadata``): the run's ``RunSpec`` as JSON, its scenario
start (ns, host clock) and duration. A ``v2i record`` file of services started by hand carries
none: the command line gives them (``v2i replay --score --scenario S --start-at-ns T0``, the
values the services were started with), and ``run_of`` says which are missing when neither
does. Values given on the command line win over recorded ones. For a file without run
metadata the duration defaults to the recorded span of RSU traffic after the start, the OBU's
wire to the recorded lists' encoding, and the profile label to ``recorded`` (the link is not run
again: its effects are in the recording).
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from schemas.list_wire import STANDARD_WIRES
from v2i.offline.spec import RunSpec

RUN_METADATA = "run"
REQUIRED_FLAGS = {"scenario": "--scenario", "start_ns": "--start-at-ns"}  # what a score cannot guess
RSU_TRAFFIC = "v2x/rsu/**"


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


def run_of(recording, given: dict[str, Any]) -> tuple[RunSpec, int]:
    """(spec, scenario start in ns) of ``recording`` (a ``v2i.telemetry.mcap_reader.Recording``):
    its run metadata, with the values ``given`` (``RunSpec`` fields and ``start_ns``; None: not
    given) over it. ValueError naming the flags to give when neither has the scenario or start."""
    metadata = recording.metadata.get(RUN_METADATA, {})
    if "spec" in metadata:
        values = {**dataclasses.asdict(spec_of(metadata)), "start_ns": int(metadata["start_ns"])}
    else:
        values = {"profile": "recorded", "wire": recorded_wire(recording)}
    values.update({k: v for k, v in given.items() if v is not None})
    missing = [flag for field, flag in REQUIRED_FLAGS.items() if field not in values]
    if missing:
        raise ValueError(f"{recording.path} has no run metadata (a v2i record file; v2i demo --record writes it): "
                         f"give {' and '.join(missing)}, as the recorded services were started")
    start_ns = int(values.pop("start_ns"))
    known = {f.name for f in dataclasses.fields(RunSpec)}
    spec = RunSpec(**{k: v for k, v in values.items() if k in known})
    if spec.duration_s is None:
        spec = dataclasses.replace(spec, duration_s=recorded_span_s(recording, start_ns))
    return spec, start_ns


def recorded_wire(recording) -> str:
    """The encoding of the recorded RSU object lists: cpm or sdsm when such lists were heard, else v2i."""
    kinds = {c.kind for c in recording.channels.values()}
    return next((wire for wire in STANDARD_WIRES if wire in kinds), "v2i")


def recorded_span_s(recording, start_ns: int) -> float:
    """Seconds from ``start_ns`` to the last recorded RSU sample (0.1 s steps, rounded up);
    ValueError when there is none after the start."""
    last_ns = max((s.log_time_ns for side in recording.sides for s in recording.samples(side, RSU_TRAFFIC)),
                  default=None)
    if last_ns is None or last_ns <= start_ns:
        where = "no RSU traffic" if last_ns is None else f"its last RSU sample at {last_ns} ns"
        raise ValueError(f"{recording.path}: {where}, none after --start-at-ns {start_ns}")
    return -(-(last_ns - start_ns) // 100_000_000) / 10
