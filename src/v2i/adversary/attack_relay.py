"""Relaying the OBU's time queries to the genuine RSU (``v2i attack`` kinds ``time_doubled``, ``time_delayed``).

The attacker holds no key: it answers the OBU's query (its queryable on ``v2x/rsu/{rsu_id}/time``
at the OBU's endpoint) with the genuine RSU's own signed replies, got by forwarding the very same
query bytes to the RSU over the session that reaches it (``--sniff``). What it can do with them:

- ``copies``: return each genuine reply this many times (``time_doubled``: 2). Before issue 32's
  fix the OBU voided two different replies to one request, so a relay stopped its clock;
- ``delay_ns``: hold each query this long before forwarding it (``time_delayed``: 100 ms), so the
  RSU stamps t2 / t3 late and the reply's round trip is longer on the request leg alone: the
  offset an exchange gives is biased by half the delay, which the clock filter must discount and
  never take for a step.

The RSU answers one copy of a query (``rsu_service.time_answers``): whichever of the attacker's
forward and the link emulator's relay reaches it first; the other gets nothing (``unanswered``).

A Zenoh query stays open until its ``Query`` is dropped: each is kept, replied to from the
forward's reply callback, and dropped when the forward is done (or when the relay stops). One
worker thread forwards the due queries in order; at most ``MAX_PENDING`` wait (the oldest is
dropped unanswered beyond, counted ``dropped``).
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections import Counter

import zenoh

from schemas import keys

MAX_PENDING = 256  # queries held for their delay at most (10 Hz x 100 ms needs 1)
FORWARD_TIMEOUT_S = 2.0  # the RSU answers at once or never (a repeat): a forward is over after this


class TimeRelay:
    """Forwards each time query of the OBU to the RSU through ``session`` and returns its replies.

    ``counts``: ``queries`` (heard from the OBU), ``forwarded``, ``rsu_replies`` (genuine replies
    the RSU sent back), ``returned`` (copies sent to the OBU), ``unanswered`` (forwards the RSU did
    not answer: it had answered that query already), ``dropped`` (held beyond ``MAX_PENDING``),
    ``not_a_request`` (a query without a payload)."""

    def __init__(self, session, rsu_id: str, copies: int = 1, delay_ns: int = 0,
                 timeout_s: float = FORWARD_TIMEOUT_S):
        if copies < 1 or delay_ns < 0:
            raise ValueError(f"a relay returns >= 1 copy after >= 0 ns (got {copies}, {delay_ns} ns)")
        self.session, self.key = session, keys.rsu_time(keys.check_id(rsu_id))
        self.copies, self.delay_ns, self.timeout_s = copies, delay_ns, timeout_s
        self.counts: Counter = Counter()
        self.first_query_ns: int | None = None  # when the first query came (Unix ns)
        self._lock = threading.Lock()  # counts and the due heap: callbacks, the worker, the caller
        self._wake = threading.Condition(self._lock)
        self._due: list[tuple[int, int, bytes, object]] = []  # (due monotonic ns, tie, query bytes, query)
        self._tie = itertools.count()
        self._stopped = False
        self._worker = threading.Thread(target=self._run, name="time-relay", daemon=True)
        self._worker.start()

    # --- Zenoh callback thread --------------------------------------------------------------------
    def on_query(self, query) -> None:
        """A query of the OBU: held for ``delay_ns``, then forwarded (the worker does)."""
        payload = query.payload
        with self._lock:
            self.counts["queries"] += 1
            self.first_query_ns = self.first_query_ns or time.time_ns()
            if payload is None or self._stopped:
                self.counts["not_a_request" if payload is None else "dropped"] += 1
                query.drop()
                return
            heapq.heappush(self._due, (time.monotonic_ns() + self.delay_ns, next(self._tie), payload.to_bytes(), query))
            while len(self._due) > MAX_PENDING:
                oldest = min(self._due)
                self._due.remove(oldest)
                heapq.heapify(self._due)
                self.counts["dropped"] += 1
                oldest[3].drop()
            self._wake.notify()

    # --- the worker -------------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._lock:
                while not self._stopped and (not self._due or self._due[0][0] > time.monotonic_ns()):
                    wait_ns = self._due[0][0] - time.monotonic_ns() if self._due else None
                    self._wake.wait(None if wait_ns is None else max(wait_ns, 0) * 1e-9)
                if self._stopped:
                    return
                _, _, data, query = heapq.heappop(self._due)
                self.counts["forwarded"] += 1
            self._forward(data, query)

    def _forward(self, data: bytes, query) -> None:
        """The query's bytes to the RSU; each genuine reply back to the OBU ``copies`` times."""
        answered = []

        def on_reply(reply) -> None:
            if reply.ok is None:
                return
            signed = reply.ok.payload.to_bytes()
            answered.append(True)
            for _ in range(self.copies):
                query.reply(self.key, signed)
            with self._lock:
                self.counts["rsu_replies"] += 1
                self.counts["returned"] += self.copies

        def on_done() -> None:
            if not answered:
                with self._lock:
                    self.counts["unanswered"] += 1
            query.drop()

        try:
            self.session.get(self.key, zenoh.handlers.Callback(on_reply, on_done), payload=data,
                             timeout=self.timeout_s, consolidation=zenoh.ConsolidationMode.NONE)
        except zenoh.ZError:  # the session is closing
            query.drop()

    def stop(self) -> dict[str, int]:
        """No more forwards; the held queries dropped unanswered; the counts."""
        with self._lock:
            self._stopped = True
            held, self._due = self._due, []
            if held:
                self.counts["dropped"] += len(held)
            self._wake.notify()
        for *_, query in held:
            query.drop()
        self._worker.join(2.0)
        with self._lock:
            return dict(self.counts)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counts)
