"""The player of ``v2i replay``: a ``v2i record`` file's samples republished on their keys, every stamp
moved to the replay's time zero, the recorded RSU clocks answered from the recorder's exchanges.

Design (what a replayed OBU must see to behave as the recorded one did): ``v2i.replay``. Used by
``v2i replay`` and by the scored replay (``v2i.orchestration.replay_demo``).
"""

from __future__ import annotations

import threading
import time
from collections import Counter

import numpy as np

LATE_NS = 5_000_000  # a sample published this late is counted as late


class Replayer:
    """Publishes ``recording``'s samples of ``side`` matching ``pattern`` on a Zenoh session."""

    def __init__(self, recording, side: str | None = None, pattern: str = "v2x/rsu/**", speed: float = 1.0,
                 recorded_start_ns: int | None = None):
        """``recorded_start_ns``: L0, the recorded run's start (default: its run metadata's, if any)."""
        from v2i.telemetry.time_shift import RsuClockTrack

        if not speed > 0:
            raise ValueError(f"--speed must be > 0, got {speed:g}")
        sides = recording.sides
        if side is None:
            side = "vehicle" if "vehicle" in sides else sides[0] if len(sides) == 1 else None
            if side is None:
                raise ValueError(f"{recording.path}: several sides {sides}; choose one with --side")
        elif side not in sides:
            raise ValueError(f"--side {side}: the recording has {', '.join(sides) or 'none'}")
        self.recording, self.side, self.pattern, self.speed = recording, side, pattern, speed
        self.clocks = {rsu: RsuClockTrack(ex) for rsu, ex in recording.exchanges().items()}
        run = recording.metadata.get("run", {})
        if recorded_start_ns is None and "start_ns" in run:
            recorded_start_ns = int(run["start_ns"])
        self.recorded_start_ns = recorded_start_ns
        self.counts: Counter = Counter()
        self.lateness_ns: list[int] = []
        self.t0_ns = self.l0_ns = 0

    def reference_ns(self) -> int:
        """L0: the recorded run's start, else the first replayed sample's log time."""
        if self.recorded_start_ns is not None:
            return self.recorded_start_ns
        first = next(self.recording.samples(self.side, self.pattern), None)
        if first is None:
            raise ValueError(f"{self.recording.path}: no sample of side {self.side} matches {self.pattern}")
        return first.log_time_ns

    def align(self, t0_ns: int) -> int:
        """Fix the mapping L0 -> ``t0_ns`` (moved to a whole ms of shift); returns the T0 used."""
        from v2i.telemetry.time_shift import round_shift_ns

        self.l0_ns = self.reference_ns()
        self.t0_ns = self.l0_ns + round_shift_ns(t0_ns - self.l0_ns)
        return self.t0_ns

    def recorded_time_ns(self, t_ns: int) -> int:
        """Recorded host time of replay time ``t_ns``: L0 + (t - T0) * speed."""
        return self.l0_ns + round((t_ns - self.t0_ns) * self.speed)

    # ------------------------------------------------------------------ Zenoh shell
    def declare_clocks(self, session) -> list:
        """A time queryable per recorded RSU (answered in the callback, like the RSU)."""
        from schemas import keys

        return [session.declare_queryable(keys.rsu_time(rsu), lambda q, r=rsu: self._answer(q, r))
                for rsu, track in self.clocks.items() if track]

    def _answer(self, query, rsu_id: str) -> None:
        from schemas import keys
        from schemas.codec import CodecError, decode, encode
        from schemas.messages import TimeReply, TimeRequest

        now_ns = time.time_ns()
        try:
            request = decode(query.payload.to_bytes() if query.payload is not None else b"", TimeRequest, 4096)
        except CodecError:
            self.counts["time_query_refused"] += 1
            return
        rsu_ns = now_ns + self.clocks[rsu_id].offset_at(self.recorded_time_ns(now_ns))
        query.reply(keys.rsu_time(rsu_id), encode(TimeReply(rsu_id=rsu_id, seq=request.seq, t1_ns=request.t1_ns,
                                                            t2_ns=rsu_ns, t3_ns=rsu_ns)))
        self.counts["time_replies"] += 1

    def play(self, session, stop: threading.Event) -> None:
        """Publish every selected sample at its time (``align`` first); returns at the end or on ``stop``."""
        from v2i.telemetry.time_shift import shift_payload

        publishers = {}
        for sample in self.recording.samples(self.side, self.pattern):
            due_ns = self.t0_ns + round((sample.log_time_ns - self.l0_ns) / self.speed)
            payload = self._shifted(sample, due_ns, shift_payload)
            if stop.wait(max(due_ns - time.time_ns(), 0) * 1e-9):
                return
            if sample.key not in publishers:
                publishers[sample.key] = session.declare_publisher(sample.key)
            publishers[sample.key].put(payload)
            late_ns = time.time_ns() - due_ns
            self.lateness_ns.append(late_ns)
            self.counts["published"] += 1
            self.counts["late"] += late_ns > LATE_NS
        for publisher in publishers.values():
            publisher.undeclare()

    def _shifted(self, sample, due_ns: int, shift_payload) -> bytes:
        from schemas.codec import CodecError
        from schemas.keys import rsu_id_or_none
        from v2i.telemetry.time_shift import round_shift_ns

        shift_ns = (self.t0_ns - self.l0_ns) if self.speed == 1.0 else round_shift_ns(due_ns - sample.log_time_ns)
        try:
            shifted = shift_payload(sample.kind, sample.model, sample.content, shift_ns, rsu_id_or_none(sample.key))
        except (CodecError, ValueError):
            self.counts["unshifted"] += 1
            return sample.payload
        self.counts["envelopes_removed"] += sample.signed
        return shifted

    def stats(self) -> dict:
        """Counts, lateness percentiles (ms) and the RSU clocks used."""
        late = np.array(self.lateness_ns, dtype=float) * 1e-6
        pct = {f"p{q}": round(float(np.percentile(late, q)), 3) for q in (50, 95, 99)} if len(late) else {}
        return {"side": self.side, "keys": self.pattern, "speed": self.speed, "shift_ns": self.t0_ns - self.l0_ns,
                **{k: int(v) for k, v in sorted(self.counts.items())},
                "lateness_ms": {**pct, "max": round(float(late.max()), 3) if len(late) else None},
                "rsu_clocks": {rsu: {"exchanges_used": t.used, "exchanges_dropped": t.dropped}
                               for rsu, t in self.clocks.items()}}
