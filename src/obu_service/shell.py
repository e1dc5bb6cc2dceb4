"""The OBU nodes' shared Zenoh shell (``ObuShell``): what the object-level node (``node.ObuNode``)
and the image-level one (``image_fusion_node.ImageFusionNode``) both do around their pipeline.

- The intake: Zenoh callbacks only stamp the receive time and put the payload into a bounded,
  rate-limited ``Intake`` (``_put``; the node says whose keys are served first).
- The run: open the session, declare (the node's ``_declare``), say ready, wait for time zero
  (``v2i.runtime.process.start_when_told``), schedule and loop (the node's ``_schedule`` and
  ``_loop``), then undeclare, close and log the node's closing line (``_stopped``).
- The timed events: typed values on one ``v2i.core.scheduler.Timeline``, fired in due order, at
  one time by ``RANK``, then as pushed (``_at``); the time-sync exchanges and the run's end (``_schedule_syncs``; without a
  duration the run goes on until stopped and each exchange schedules the next).
- The time queries to every RSU (``_query_time``, replies through the intake), the refusals
  counted into the pipeline and the throttled log, a trust change (revocation) logged.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import zenoh

from v2i.core.clock import Clock, SystemClock
from v2i.core.scheduler import Timeline
from schemas import keys
from schemas.codec import encode
from schemas.messages import TimeRequest
from v2i.clock.time_requests import sync_times_ns
from v2i.runtime.intake import Intake
from v2i.runtime.process import MemoryTrim, ThrottledLog, announce, log, read_start_line, start_when_told
from v2i.runtime.transport import open_session

from obu_service.config import ObuConfig
from obu_service.inbound_security import envelope_screen

CROWDED_WINDOW_S = 1.0  # a cycle that fell back this soon after a registered input was refused: crowded out
# the planner-facing outputs must not be dropped under load: block, real-time, unbatched
CRITICAL = dict(congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.REAL_TIME, express=True)


# --- the timed events both nodes have (each node adds its own): at one time by RANK, then as pushed ---
@dataclass(frozen=True)
class Deadline:
    """A cycle's (an image frame's) fuse-by time: it goes out now if it still waits."""

    RANK: ClassVar[int] = 0


@dataclass(frozen=True)
class Capture:
    """The own sensor samples at the event's time (--source sim: LiDAR and localisation; roif: the camera)."""

    RANK: ClassVar[int] = 2


@dataclass(frozen=True)
class Sync:
    """A time-sync exchange with the RSUs (and the V2V peers)."""

    RANK: ClassVar[int] = 4


@dataclass(frozen=True)
class End:
    """The run's end (its duration and a second after)."""

    RANK: ClassVar[int] = 5


def direct_callback(callback: Callable) -> Callable | zenoh.handlers.Callback:
    """``callback`` run on the Zenoh thread that receives (no Python thread started per query): for
    callbacks that only stamp and enqueue. ``indirect`` is unstable in zenoh-python; without it, the
    plain callback."""
    try:
        return zenoh.handlers.Callback(callback, indirect=False)
    except TypeError:
        return callback


class ObuShell:
    """The shell an OBU node is: subclasses give ``pipeline`` (with ``reject``, ``rejected``), ``_security``,
    ``_begin``, ``_declare``, ``_schedule``, ``_loop`` and ``_stopped``."""

    READY: ClassVar[dict] = {}  # more fields of the ready line

    def __init__(self, config: ObuConfig, clock: Clock | None, preferred: Callable[[str], bool],
                 signed_kinds: frozenset[str] = frozenset()):
        """``preferred(key)``: whose inputs the intake serves first (registered RSUs, own sensors);
        ``signed_kinds``: the kinds verified before they are read, whose rate budget is the verified
        signer's (``inbound_security``) and, before verification, the intake's unverified one; none
        under policy off."""
        self.config = config
        self.name = f"obu {config.vehicle_id}"  # in its log lines
        self.clock = clock or SystemClock()
        self.start_ns: int | None = None  # time zero (OBU clock), from _begin
        self.duration_s = config.duration_s  # None: until stopped
        signed = signed_kinds if config.security_policy != "off" else frozenset()
        self._intake = Intake(config.inbox_capacity, config.max_message_bytes, config.source_rate_hz,
                              config.source_burst, max_queued_bytes=config.inbox_max_bytes, preferred=preferred,
                              signed_kinds=signed, screen=envelope_screen(config.security_policy))
        self._log, self._trim = ThrottledLog(self.name), MemoryTrim()
        self._details: dict[str, str] = {}  # first codec error message per reason
        self._events: Timeline = Timeline()  # the node's timed events (their RANK: which of one time first)

    def _begin_unless_awaited(self) -> None:
        """Time zero now (``config.start_at_ns`` or the clock), unless ``config.await_start``: then after
        the ready line."""
        if not self.config.await_start:
            self._begin(self.config.start_at_ns or self.clock.now_ns())

    def run(self, stop: threading.Event, await_start=read_start_line) -> None:
        """Declare, say ready, (``await_start``: wait for time zero, ``v2i.runtime.process.start_when_told``),
        then run until the run's end or ``stop``."""
        session = open_session(self.config.listen, self.config.connect)
        entities: list = []
        try:
            self._declare(session, entities)
            self._session = session
            announce("ready", "obu", vehicle_id=self.config.vehicle_id, listen=self.config.listen, **self.READY)
            if self.start_ns is None and not start_when_told(self.name, stop, self._begin, self.clock.now_ns,
                                                             await_start):
                return
            self._schedule()
            self._loop(stop)
        finally:
            for entity in entities:
                entity.undeclare()
            session.close()
            self._log.flush(force=True)
            log(self.name, self._stopped())

    # --- Zenoh callbacks: stamp and enqueue only ---------------------------------------
    def _on_time_reply(self, reply) -> None:
        if reply.ok is not None:
            self._put("time", reply.ok)

    def _put(self, kind: str, sample) -> None:
        payload = sample.payload
        self._intake.put(kind, str(sample.key_expr), len(payload), self.clock.now_ns(), payload.to_bytes)

    # --- timed events ----------------------------------------------------------------------
    def _at(self, due_ns: int, event) -> None:
        """Fire ``event`` at ``due_ns`` (OBU clock); at one time by its ``RANK``, then as pushed."""
        self._events.push(due_ns, event, event.RANK)

    def _schedule_syncs(self, now_ns: int) -> None:
        """The run's time-sync exchanges and its end; without a duration the first exchange only (each
        schedules the next: ``_next_sync``) and no end."""
        if self.duration_s is None:
            lead = sync_times_ns(now_ns, self.start_ns, 0.0, self.config.sync_rate_hz)  # those before time zero
            self._at(lead[0] if lead else now_ns, Sync())
            return
        for t in sync_times_ns(now_ns, self.start_ns, self.duration_s, self.config.sync_rate_hz):
            self._at(t, Sync())
        self._at(self.start_ns + round((self.duration_s + 1.0) * 1e9), End())

    def _next_sync(self, due_ns: int) -> None:
        """Until stopped: the exchange after the one due at ``due_ns``."""
        if self.duration_s is None:
            self._at(due_ns + round(1e9 / self.config.sync_rate_hz), Sync())

    # --- out -----------------------------------------------------------------------------
    def _query_time(self, request: TimeRequest) -> None:
        """A time request to every RSU; every reply, unmerged (two replies on one RSU's key are a conflict
        the pipeline must see), comes through the intake.

        t1 (``request.t1_ns``) is stamped before this call, so whatever ``get`` does before the query
        leaves lengthens the uplink leg alone and biases the offset estimate by half of it (theta_hat =
        theta + (d_up - d_down) / 2). zenoh-python's default callback handler starts a Python thread for
        every ``get`` first (0.25-0.3 ms here); a direct handler does not (``direct_callback``)."""
        self._session.get(keys.RSU_TIME_ALL, direct_callback(self._on_time_reply), payload=encode(request),
                          timeout=self.config.time_query_timeout_s, consolidation=zenoh.ConsolidationMode.NONE)

    def _count_refusals(self) -> None:
        """The intake's refusals into the pipeline's counters; the new ones to the throttled log."""
        for reason, n in self._intake.take_counts().items():
            self.pipeline.reject(reason, n)
        # an RSU or a peer that sees this vehicle reports it too: dropping that is normal work, not a refusal
        # worth a log line (still counted in the metrics)
        refused = {r: n for r, n in self.pipeline.rejected.items() if not r.endswith("ego_self_detection")}
        self._log.totals(refused, self._details)

    def _charge_if_unverified(self, source: str) -> None:
        """After a signed message of ``source`` went through ``self._security``: if it failed verification,
        it draws from its source's unverified budget (``Intake.charge_unverified``)."""
        if self._security.checks and not self._security.verified:
            self._intake.charge_unverified(source)

    def _count_crowded_out(self, mode_reason: str) -> None:
        """A cycle that did not run its best mode (``mode_reason`` other than ``best``) within
        ``CROWDED_WINDOW_S`` of the intake refusing a preferred source's message (a registered RSU's, an
        own sensor's) fell back because genuine input was crowded out (``ObuMetrics.crowded_out_cycles``)."""
        if mode_reason != "best" and self._intake.crowded_within(round(CROWDED_WINDOW_S * 1e9)):
            self.pipeline.crowded_out_cycles += 1

    def _poll_trust(self) -> None:
        """A change of the site's trust (a revocation while running), logged; and a site whose messages
        have all failed verification for a while (a wrong CA?), warned about once."""
        now_ns = self.clock.now_ns()
        if (change := self._security.poll_trust(now_ns)) is not None:
            log(self.name, change)
        if (warning := self._security.silence_warning(now_ns)) is not None:
            log(self.name, warning)
