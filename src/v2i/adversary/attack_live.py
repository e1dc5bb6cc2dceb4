"""The live driver of ``v2i attack`` (see ``v2i.adversary.attack``): sessions, phases, accounting.

One main thread paces the sends and drains the inbox the callbacks fill; the time queryable
answers in its callback (a Zenoh query is answered there), reading the attacker's clock estimate
and its reply budget under a lock.
"""

from __future__ import annotations

import itertools
import json
import queue
import statistics
import sys
import threading
import time
from collections import Counter, deque

import numpy as np

from v2i.core.frames import Pose2D
from schemas import keys
from schemas.codec import CodecError, decode
from schemas.limits import SOURCE_RSU
from schemas.messages import EgoPose, FusedObjectList, ObjectList, ObuMetrics, TimeRequest
from v2i.runtime.transport import open_session
from v2i.security.envelope import PREFIX, parse
from v2i.telemetry.live_line import StatusLine

from v2i.adversary.attack_ghosts import GhostWatch
from v2i.adversary.attack_hostile import PROGRESS_S, HostilePhases, NotReady, rsu_status
from v2i.adversary.attack_messages import (CONTROL_VARIANTS, HOSTILE_KINDS, LIST_KINDS, TIME_VARIANTS, AttackerKeys,
                                           AttackMessages, ghost_xy, signer_digest)
from v2i.adversary.attack_report import counter_delta, kind_row

REPLAY_AGE_NS = (500_000_000, 3_000_000_000)  # replay captures this old: after the original, within freshness
INBOX_MESSAGES = 10_000
READY_TIMEOUT_S = 120.0  # default --ready-timeout: the site shows what the attack needs within this
OFFSET_SAMPLES = 32  # RSU clock offset: median of the latest this many captures
METRICS_KEPT = 20_000  # OBU metrics kept for the windows of the opt-in kinds: 10 Hz x 33 min


class AttackRun(HostilePhases):
    def __init__(self, args, kinds: list[str], attacker: AttackerKeys):
        self.args, self.kinds = args, kinds
        self.rng = np.random.default_rng(args.seed)
        self.attacker = attacker
        self.messages: AttackMessages | None = None  # once the genuine digest is known
        self.inbox: queue.Queue = queue.Queue(INBOX_MESSAGES)
        self.dropped = 0
        self.lock = threading.Lock()  # the time queryable's view: offsets, budget, sent
        self.offsets: deque[int] = deque(maxlen=OFFSET_SAMPLES)  # RSU clock - local clock, ns
        self.time_budget, self.time_sent = 0, Counter()
        self.captured: deque[tuple[int, bytes]] = deque(maxlen=128)  # (local receive ns, genuine envelope)
        self.digest: bytes | None = None
        self.watch = GhostWatch()
        self.pose: EgoPose | None = None
        self.metrics: ObuMetrics | None = None
        self.link_stats: dict = {}
        self.link_stats_ns = 0
        self.outputs: list[tuple[int, int, int, bool]] = []  # (cycle ns, ghosts, decoy ghosts, has RSU objects)
        self.genuine_lists: list[int] = []  # local receive ns of each sniffed genuine list
        self.rows: dict[str, dict] = {}
        self.clock_rows: list[tuple[int, int]] = []  # (t_ns, OBU's offset estimate of the RSU)
        self.metrics_log: deque[ObuMetrics] = deque(maxlen=METRICS_KEPT)  # every OBU metrics message, in order
        self.relay = None  # a TimeRelay while a relay kind runs: the time queryable hands it the queries
        self.sniff = None  # the session that reaches the RSU
        self._sessions, self._declared = [], []
        self._decoys = False
        self._marks: dict[str, tuple] = {}

    # --- sessions ---------------------------------------------------------------------------------
    def open(self) -> None:
        a, vid = self.args, self.args.vehicle_id
        sniff = self.sniff = self._session(a.sniff)
        self._declare(sniff.declare_subscriber(keys.rsu_objects(a.rsu_id), lambda s: self._put("genuine", s)))
        self.vehicle = self._session(a.connect)
        for kind, key in (("pose", keys.obu_pose(vid)), ("fused", keys.obu_objects(vid)),
                          ("metrics", keys.obu_metrics(vid))):
            self._declare(self.vehicle.declare_subscriber(key, lambda s, kind=kind: self._put(kind, s)))
        self._declare(self.vehicle.declare_queryable(keys.rsu_time(a.rsu_id), self._on_time_query))
        self.publisher = self._declare(self.vehicle.declare_publisher(keys.rsu_objects(a.rsu_id)))
        self.control = None
        if a.control:
            control = self._session(a.control)
            self._declare(control.declare_subscriber(keys.link_stats(a.link_id), lambda s: self._put("stats", s)))
            self.control = self._declare(control.declare_publisher(keys.link_control(a.link_id)))

    def _session(self, endpoint: str):
        session = open_session(connect=[endpoint])
        self._sessions.append(session)
        return session

    def _declare(self, entity):
        self._declared.append(entity)
        return entity

    def close(self) -> None:
        if self.relay is not None:
            self.relay.stop()
            self.relay = None
        for entity in self._declared:
            entity.undeclare()
        for session in self._sessions:
            session.close()
        self._declared, self._sessions = [], []

    def _put(self, kind: str, sample) -> None:
        try:
            self.inbox.put_nowait((kind, time.time_ns(), sample.payload.to_bytes()))
        except queue.Full:
            self.dropped += 1

    # --- what came in -----------------------------------------------------------------------------
    def pump(self, until: float) -> None:
        """Handle inputs until monotonic time ``until``."""
        while (left := until - time.monotonic()) > 0:
            try:
                kind, t_ns, data = self.inbox.get(timeout=min(left, 0.01))
            except queue.Empty:
                continue
            try:
                getattr(self, f"_on_{kind}")(t_ns, data)
            except (CodecError, ValueError, KeyError, TypeError):
                continue  # a message the attacker cannot read: nothing to learn from it

    def _on_genuine(self, t_ns: int, data: bytes) -> None:
        envelope = parse(data) if data.startswith(PREFIX) else None
        payload = envelope.payload if envelope else data
        listed = decode(payload, ObjectList)
        stamp_ns = envelope.generation_ns if envelope else listed.header.publish_time_ns
        with self.lock:
            self.offsets.append(stamp_ns - t_ns)
        self.genuine_lists.append(t_ns)
        if envelope is not None:
            self.captured.append((t_ns, data))
            self.digest = self.digest or signer_digest(data)
        objs = listed.objects
        capture_local_ns = listed.header.capture_time_ns - self.rsu_offset_ns()
        self.watch.genuine(capture_local_ns, np.column_stack([objs.column("x"), objs.column("y")]),
                           np.column_stack([objs.column("vx"), objs.column("vy")]))

    def _on_pose(self, t_ns: int, data: bytes) -> None:
        self.pose = decode(data, EgoPose)

    def _on_fused(self, t_ns: int, data: bytes) -> None:
        out = decode(data, FusedObjectList)
        has_rsu = bool(len(out.objects)) and bool((out.objects.column("sources").astype(int) & SOURCE_RSU).any())
        self.outputs.append((out.cycle_time_ns, self.watch.ghosts_in(out), self.watch.ghosts_in(out, decoy=True),
                             has_rsu))

    def _on_metrics(self, t_ns: int, data: bytes) -> None:
        self.metrics = decode(data, ObuMetrics)
        self.metrics_log.append(self.metrics)
        for r in self.metrics.rsus:
            if r.rsu_id == self.args.rsu_id and r.clock_offset_ns is not None:
                self.clock_rows.append((self.metrics.t_ns, r.clock_offset_ns))

    def _on_stats(self, t_ns: int, data: bytes) -> None:
        self.link_stats, self.link_stats_ns = json.loads(data), t_ns

    def rsu_offset_ns(self) -> int:
        with self.lock:
            return int(statistics.median(self.offsets)) if self.offsets else 0

    def _ego_at(self, t_ns: int) -> Pose2D:
        """The ego pose extrapolated to ``t_ns`` at its velocity: p(t) = p + v (t - t_pose)."""
        p, dt_s = self.pose, (t_ns - self.pose.t_ns) * 1e-9
        return Pose2D(p.x + p.vx * dt_s, p.y + p.vy * dt_s, p.yaw, p.vx, p.vy)

    # --- the time queryable (Zenoh callback thread) -----------------------------------------------
    def _on_time_query(self, query) -> None:
        relay = self.relay
        if relay is not None:  # a relay kind: the genuine RSU's replies, not forged ones
            relay.on_query(query)
            return
        try:
            request = decode(query.payload.to_bytes(), TimeRequest)
        except (CodecError, AttributeError):
            return
        with self.lock:
            n = min(self.time_budget, self.args.time_burst)
            self.time_budget -= n
            offset_ns = int(statistics.median(self.offsets)) if self.offsets else 0
        for i in range(n):
            variant = TIME_VARIANTS[i % len(TIME_VARIANTS)]
            query.reply(keys.rsu_time(self.args.rsu_id), self.messages.time_reply(request, offset_ns, variant))
            with self.lock:
                self.time_sent[variant] += 1

    # --- the run ----------------------------------------------------------------------------------
    def run(self) -> dict:
        self.open()
        kinds = list(self.kinds)
        if getattr(self.args, "from_start", False):  # a relay kind from the OBU's first query on
            self.announce_ready()
            self._phase(kinds.pop(0))
            if not kinds:
                return self.report()
        self._wait_ready()
        self._baseline()
        for kind in kinds:
            self._phase(kind)
        return self.report()

    def _missing(self) -> list[str]:
        """What the attack needs and has not seen yet (its words, for the progress line and the error)."""
        status = rsu_status(self.metrics, self.args.rsu_id)
        return [what for what, ok in (
            ("genuine signed lists of the RSU (is it signing? --sniff reaches it?)", len(self.captured) >= 3),
            ("the ego's pose", self.pose is not None),
            ("OBU metrics with an RSU clock estimate and accepted lists",
             status is not None and status.clock_offset_ns is not None and status.messages_accepted > 0))
            if not ok]

    def _wait_ready(self) -> None:
        """Until the site shows what the attack needs, at most ``--ready-timeout`` s (one bound: a site
        started at the same time on a busy machine takes its time); a progress line on stderr meanwhile."""
        timeout_s = getattr(self.args, "ready_timeout", None) or READY_TIMEOUT_S
        t0 = time.monotonic()
        missing = self._missing()
        line = StatusLine(lambda: f"v2i attack: waiting for {'; '.join(missing) or 'nothing'} "
                                  f"({time.monotonic() - t0:.1f} s)")
        line.start()
        try:
            while missing and time.monotonic() - t0 < timeout_s:
                self.pump(time.monotonic() + 0.1)
                missing = self._missing()
        finally:
            line.stop()
        if missing:
            raise NotReady(f"not ready within {timeout_s:g} s (--ready-timeout): still waiting for {'; '.join(missing)}")
        self.messages = AttackMessages(self.args.rsu_id, self.attacker, self.rng, self.digest, self.args.link_id)

    def _snapshot(self) -> tuple:
        status = rsu_status(self.metrics, self.args.rsu_id)
        control = self.link_stats.get("control", {}) if self.link_stats else {}
        m = self.metrics
        return (time.time_ns(), dict(m.rejected) if m else {}, dict(control.get("rejected", {})),
                control.get("applied", 0), len(self.outputs), len(self.genuine_lists),
                status.messages_accepted if status else 0, m.output_deadline_misses if m else 0, m.cycles if m else 0)

    def _baseline(self) -> None:
        """Genuine traffic only, decoy ghosts placed where real ones would go."""
        start = self._snapshot()
        end = time.monotonic() + self.args.warmup_s
        while time.monotonic() < end:
            now_ns = time.time_ns()
            self.watch.place(now_ns, ghost_xy(self._ego_at(now_ns)), decoy=True)
            self.pump(min(end, time.monotonic() + 1.0 / self.args.rate_hz))
        self._settled(self.args.settle_s)
        self._marks["baseline"] = (start, self._snapshot())
        self._marks["attack_start"] = self._marks["baseline"][1]

    def _settled(self, settle_s: float) -> None:
        """Wait ``settle_s``, then for OBU metrics (and link stats) stamped after it, up to 3 s more."""
        until_ns = time.time_ns() + round(settle_s * 1e9)
        self.pump(time.monotonic() + settle_s)
        end = time.monotonic() + 3.0
        while time.monotonic() < end and (self.metrics is None or self.metrics.t_ns < until_ns or
                                          (self.control is not None and self.link_stats_ns < until_ns)):
            self.pump(time.monotonic() + 0.05)

    def _phase(self, kind: str) -> None:
        if kind in HOSTILE_KINDS:
            self.rows[kind] = self._phase_flood() if kind == "flood" else self._phase_relay(kind)
            return
        before, t0 = self._snapshot(), time.monotonic()
        clock_from = len(self.clock_rows)
        if kind == "time":
            sent = self._send_time()
        else:
            sent = self._send_paced(kind)
        self._settled(self.args.settle_s)
        after = self._snapshot()
        self._marks[kind] = (before, after)
        ghosts = [(g, has) for t, g, _, has in self.outputs[before[4]:after[4]]]
        shift = None
        if kind == "time":
            base = self.clock_rows[clock_from - 1][1] if clock_from else None
            during = [o for _, o in self.clock_rows[clock_from:]]
            shift = max((abs(o - base) for o in during), default=0) / 1e6 if base is not None else None
        self.rows[kind] = kind_row(
            kind, sent, counter_delta(after[1], before[1]), sum(1 for g, _ in ghosts if g),
            sum(g for g, _ in ghosts), len(ghosts), time.monotonic() - t0,
            control_delta=counter_delta(after[2], before[2]) if kind == "control" else None,
            control_applied=after[3] - before[3] if kind == "control" else None, clock_shift_ms=shift)

    def _send_paced(self, kind: str) -> Counter:
        sent, start = Counter(), time.monotonic()
        last_note = start
        variants = itertools.cycle(CONTROL_VARIANTS)
        for i in range(self.args.count):
            self.pump(start + i / self.args.rate_hz)
            now_ns = time.time_ns()
            if kind == "control":
                variant = next(variants)
                _, data = self.messages.control(variant, seq=10**9 + i, generation_ns=now_ns)
                self.control.put(data)
                sent[variant] += 1
            else:
                captured = self._replayable(now_ns) if kind == "replayed" else None
                if kind == "replayed" and captured is None:
                    continue
                ego = self._ego_at(now_ns)
                _, data = self.messages.list_message(kind, now_ns + self.rsu_offset_ns(), ego, captured)
                self.publisher.put(data)
                if kind in LIST_KINDS and kind != "replayed":
                    self.watch.place(now_ns, ghost_xy(ego))
                sent[kind] += 1
            if time.monotonic() - last_note > PROGRESS_S:
                last_note = time.monotonic()
                self._progress(kind, sum(sent.values()))
        return sent

    def _replayable(self, now_ns: int) -> bytes | None:
        lo, hi = now_ns - REPLAY_AGE_NS[1], now_ns - REPLAY_AGE_NS[0]
        pool = [data for t, data in self.captured if lo <= t <= hi]
        return pool[int(self.rng.integers(len(pool)))] if pool else None

    def _send_time(self) -> Counter:
        with self.lock:
            self.time_budget, self.time_sent = self.args.count, Counter()
        # the OBU asks ~10 times a second; give it 3x the time that would take, at least 10 s
        end = time.monotonic() + max(10.0, 3.0 * self.args.count / (10.0 * self.args.time_burst))
        last_note = time.monotonic()
        while time.monotonic() < end:
            self.pump(time.monotonic() + 0.1)
            with self.lock:
                done, sent = self.time_budget == 0, sum(self.time_sent.values())
            if done:
                break
            if time.monotonic() - last_note > PROGRESS_S:
                last_note = time.monotonic()
                self._progress("time", sent)
        with self.lock:
            self.time_budget = 0
            return Counter(self.time_sent)

    def _progress(self, kind: str, sent: int) -> None:
        counts = self.metrics.rejected if self.metrics else {}
        dropped = sum(v for k, v in counts.items() if k.startswith("security_") and not k.startswith("security_accepted_"))
        accepted = sum(v for k, v in counts.items() if k.startswith("security_accepted_"))
        ghosts = sum(1 for _, g, _, _ in self.outputs if g)
        print(f"v2i attack: {kind} {sent}/{self.args.count} sent; the OBU so far dropped {dropped}, accepted failing "
              f"{accepted}; outputs with a ghost {ghosts}", file=sys.stderr, flush=True)

    # --- the report -------------------------------------------------------------------------------
    def report(self) -> dict:
        """Everything measured so far (also after an interruption)."""
        start = self._marks.get("attack_start")
        end = self._snapshot()
        base = self._marks.get("baseline")
        fp = [d for _, _, d, _ in self.outputs[base[0][4]:base[1][4]]] if base else []
        genuine = {"window_s": 0.0, "rsu_lists_sniffed": 0, "rsu_lists_accepted": 0, "outputs": 0,
                   "outputs_with_rsu_objects": 0, "output_deadline_misses": 0, "cycles": 0}
        if start is not None:
            during = self.outputs[start[4]:end[4]]
            genuine = {"window_s": round((end[0] - start[0]) * 1e-9, 2), "rsu_lists_sniffed": end[5] - start[5],
                       "rsu_lists_accepted": end[6] - start[6], "outputs": len(during),
                       "outputs_with_rsu_objects": sum(1 for *_, has in during if has),
                       "output_deadline_misses": end[7] - start[7], "cycles": end[8] - start[8]}
        b0, b1 = base if base else (end, end)
        baseline = {"window_s": round((b1[0] - b0[0]) * 1e-9, 2), "rsu_lists_sniffed": b1[5] - b0[5],
                    "rsu_lists_accepted": b1[6] - b0[6], "outputs": len(fp),
                    "false_positive_outputs": sum(1 for d in fp if d),
                    "rejected": {k[len("security_"):]: v for k, v in counter_delta(b1[1], b0[1]).items()
                                 if k.startswith("security_")}}
        return {"rsu_id": self.args.rsu_id, "vehicle_id": self.args.vehicle_id, "count": self.args.count,
                "rate_hz": self.args.rate_hz, "kinds": dict(self.rows), "genuine": genuine, "baseline": baseline,
                "inbox_dropped": self.dropped}
