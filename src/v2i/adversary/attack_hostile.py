"""The opt-in kinds of ``v2i attack`` (issue 32), a part of ``AttackRun``: what a keyless attacker
takes from the genuine RSU's share of the OBU.

- ``flood``: ``--flood-rate-hz`` messages a second for ``--flood-s`` on the genuine RSU's own
  objects key (``AttackMessages.flood``: junk, unsigned and forged lists in turn). The genuine
  RSU's loss is measured between two OBU metrics messages M0 (before) and M1 (after the last
  send plus the one-way delay): lists it sent = the lists sniffed at the RSU in
  (t0 - d, t1 - d], d the OBU's ``delay_p50_ms`` for it; lists the OBU took = the growth of its
  ``messages_accepted``; with the cycles by mode, output misses and ghosts in that window.
- ``time_doubled`` / ``time_delayed``: for ``--time-s``, the OBU's time queries go to a
  :class:`v2i.adversary.attack_relay.TimeRelay` (genuine replies twice; request legs held
  ``--time-delay-ms``); the row gives the OBU's clock relation to the RSU over the window
  (samples, steps, offset and its stated uncertainty against the attacker's own estimate of the
  RSU clock), the time to its first estimate, and the cycles by mode. With ``--from-start`` the
  first kind runs from the moment the sessions are open (the site started after the attacker).
"""

from __future__ import annotations

import json
import sys
import time
from collections import Counter

from schemas.messages import ObuMetrics, RsuLinkStatus

from v2i.adversary.attack_messages import FLOOD_VARIANTS, ghost_xy
from v2i.adversary.attack_relay import TimeRelay
from v2i.adversary.attack_report import counter_delta, flood_row, genuine_sent_in, relay_row

FLOOD_PAYLOAD_NS = 20_000_000  # one ghost payload (and placement) serves the flood this long: encoding costs ~150 us
FLOOD_BATCH_S = 0.02  # a sender that fell behind catches up by at most this much of its rate at once
METRICS_WAIT_S = 5.0  # the OBU publishes metrics every cycle (10 Hz): one comes well within this
CLOCK_SAMPLE_NS = 1_000_000_000  # the row's clock samples: one a second
PROGRESS_S = 5.0


class NotReady(RuntimeError):
    """The site never showed what the attack needs (genuine lists, the ego pose, OBU metrics)."""


def rsu_status(metrics: ObuMetrics | None, rsu_id: str) -> RsuLinkStatus | None:
    """What ``metrics`` says of ``rsu_id`` (None: nothing)."""
    return next((r for r in metrics.rsus if r.rsu_id == rsu_id), None) if metrics else None


class HostilePhases:
    """The phases of ``flood``, ``time_doubled`` and ``time_delayed``; mixed into ``AttackRun``,
    whose sessions, inbox (``pump``), metrics and ghost watch they use."""

    def announce_ready(self) -> None:
        """``{"event": "ready", ...}`` on stdout: the sessions are open (a harness starts the site now)."""
        print(json.dumps({"event": "ready", "tool": "attack", "kinds": list(self.kinds)}), flush=True)

    def _metrics_after(self, t_ns: int, timeout_s: float = METRICS_WAIT_S) -> ObuMetrics | None:
        """The first OBU metrics stamped at or after ``t_ns`` (waits up to ``timeout_s``; else the latest)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and (self.metrics is None or self.metrics.t_ns < t_ns):
            self.pump(time.monotonic() + 0.02)
        return self.metrics

    # --- flood ------------------------------------------------------------------------------------
    def _phase_flood(self) -> dict:
        a, rsu_id = self.args, self.args.rsu_id
        m0 = self._metrics_after(0)
        if m0 is None:
            raise NotReady(f"no OBU metrics within {METRICS_WAIT_S:g} s")
        out0 = len(self.outputs)
        sent, send_s = self._send_flood(a.flood_rate_hz, a.flood_s)
        status = rsu_status(self.metrics, rsu_id)
        delay_ns = round((status.delay_p50_ms or 0.0) * 1e6) if status else 0
        m1 = self._metrics_after(time.time_ns() + delay_ns + 20_000_000)
        self._settled(a.settle_s)  # the flood's backlog refused and counted before the next kind
        s0, s1 = rsu_status(m0, rsu_id), rsu_status(m1, rsu_id)
        accepted = (s1.messages_accepted if s1 else 0) - (s0.messages_accepted if s0 else 0)
        ghosts = [g for _, g, _, _ in self.outputs[out0:]]
        return flood_row(sent, a.flood_rate_hz, send_s,
                         genuine_sent_in(sorted(self.genuine_lists), m0.t_ns, m1.t_ns, delay_ns), accepted,
                         counter_delta(self.metrics.rejected, m0.rejected),
                         counter_delta(m1.mode_counts, m0.mode_counts),
                         m1.output_deadline_misses - m0.output_deadline_misses, m1.cycles - m0.cycles,
                         sum(1 for g in ghosts if g), len(ghosts), (m1.t_ns - m0.t_ns) * 1e-9,
                         m1.crowded_out_cycles - m0.crowded_out_cycles)

    def _send_flood(self, rate_hz: float, duration_s: float) -> tuple[Counter, float]:
        """Flood messages in turn at ``rate_hz`` for ``duration_s``; (sent by variant, seconds sent)."""
        sent, n = Counter(), 0
        start = last_note = time.monotonic()
        batch_max = max(1, int(rate_hz * FLOOD_BATCH_S))
        payload, payload_ns = b"", -FLOOD_PAYLOAD_NS
        while (elapsed_s := time.monotonic() - start) < duration_s:
            due = min(int(elapsed_s * rate_hz) + 1 - n, batch_max)
            if due > 0:
                now_ns = time.time_ns()
                rsu_now_ns = now_ns + self.rsu_offset_ns()
                ego = self._ego_at(now_ns)
                if now_ns - payload_ns >= FLOOD_PAYLOAD_NS:
                    payload, payload_ns = self.messages.ghost_payload(rsu_now_ns, ego), now_ns
                    self.watch.place(now_ns, ghost_xy(ego))
                for _ in range(due):
                    variant = FLOOD_VARIANTS[n % len(FLOOD_VARIANTS)]
                    self.publisher.put(self.messages.flood(variant, rsu_now_ns, ego, payload))
                    sent[variant] += 1
                    n += 1
            self.pump(start + n / rate_hz)
            if time.monotonic() - last_note > PROGRESS_S:
                last_note = time.monotonic()
                self._progress_hostile(f"flood {n} sent ({n / (last_note - start):.0f}/s)")
        return sent, time.monotonic() - start

    # --- time relays ------------------------------------------------------------------------------
    def _phase_relay(self, kind: str) -> dict:
        a, rsu_id = self.args, self.args.rsu_id
        delay_ms = a.time_delay_ms if kind == "time_delayed" else 0.0
        before = self.metrics  # None: from the OBU's start
        relay = TimeRelay(self.sniff, rsu_id, copies=2 if kind == "time_doubled" else 1, delay_ns=round(delay_ms * 1e6))
        self.relay, start_ns = relay, time.time_ns()
        try:
            m0 = self._metrics_after(0, timeout_s=a.ready_timeout)
            if m0 is None:
                raise NotReady(f"no OBU metrics within {a.ready_timeout:g} s (--ready-timeout)")
            end = last_note = time.monotonic()
            end += a.time_s
            while (now := time.monotonic()) < end:
                self.pump(min(end, now + 0.5))
                if time.monotonic() - last_note > PROGRESS_S:
                    last_note = time.monotonic()
                    self._progress_hostile(f"{kind}: {relay.snapshot()}")
        finally:
            self.relay = None
            counts = relay.stop()
        m1 = self.metrics
        window = [m for m in self.metrics_log if m0.t_ns <= m.t_ns <= m1.t_ns]
        base = before or ObuMetrics(vehicle_id=m1.vehicle_id, t_ns=start_ns)
        return relay_row(counts, rsu_status(before, rsu_id), rsu_status(m1, rsu_id),
                         _first_sync_s(window, rsu_id, relay.first_query_ns or start_ns), self._reference_offset(),
                         _clock_samples(window, rsu_id), counter_delta(m1.rejected, base.rejected),
                         counter_delta(m1.mode_counts, base.mode_counts),
                         m1.output_deadline_misses - base.output_deadline_misses, m1.cycles - base.cycles,
                         (m1.t_ns - m0.t_ns) * 1e-9, delay_ms)

    def _reference_offset(self) -> int | None:
        """The attacker's estimate of the RSU clock (ns ahead of its own), None before any capture."""
        return self.rsu_offset_ns() if self.offsets else None

    def _progress_hostile(self, what: str) -> None:
        status = rsu_status(self.metrics, self.args.rsu_id)
        accepted = status.messages_accepted if status else 0
        print(f"v2i attack: {what}; the OBU accepted {accepted} genuine lists so far", file=sys.stderr, flush=True)


def _first_sync_s(window: list[ObuMetrics], rsu_id: str, since_ns: int) -> float | None:
    """Seconds from ``since_ns`` to the first metrics with a clock estimate of ``rsu_id`` (0 if the
    window starts synchronised; None: never)."""
    for m in window:
        status = rsu_status(m, rsu_id)
        if status is not None and status.clock_offset_ns is not None:
            return round(max(m.t_ns - since_ns, 0) * 1e-9, 2)
    return None


def _clock_samples(window: list[ObuMetrics], rsu_id: str) -> list[tuple[int, int, int]]:
    """(t_ns, offset_ns, uncertainty_ns) of the OBU's estimate in ``window``: one a ``CLOCK_SAMPLE_NS``, and the last."""
    rows = [(m.t_ns, s.clock_offset_ns, s.clock_uncertainty_ns or 0) for m in window
            if (s := rsu_status(m, rsu_id)) is not None and s.clock_offset_ns is not None]
    kept: list[tuple[int, int, int]] = []
    for row in rows:
        if not kept or row[0] - kept[-1][0] >= CLOCK_SAMPLE_NS:
            kept.append(row)
    if rows and kept[-1] is not rows[-1]:
        kept.append(rows[-1])
    return kept
