"""The live runs' monitor: a bounded inbox between Zenoh callbacks and one scorer thread
(``InboxScoring``, shared by ``v2i demo``, its site demo, ROIF demo and replay), and the parts of
their reports that only a live run has (how it started, the OBU's own output count)."""

from __future__ import annotations

import queue
import threading
from collections import Counter

from schemas.codec import CodecError
from v2i.runtime.process import log
from v2i.telemetry.live_line import LiveLine

from v2i.orchestration.children import START_LEAD_S, ahead_ms
from v2i.offline.spec import RunRecord

INBOX_MESSAGES = 1000  # received messages waiting to be scored (~35 s of objects, metrics and planning)


class InboxScoring:
    """The bounded inbox between Zenoh callbacks and one scorer thread, shared by the demos.

    ``_keep(kind, sample, *context)`` (a Zenoh callback) only enqueues (kind, *context, payload);
    a full inbox drops it, counted by kind in ``dropped``. ``_score_inbox`` (the scorer thread)
    calls ``self._score(kind, *context, payload)`` in arrival order until a None ends the run;
    the first scoring error is kept in ``_scoring_error`` for ``run()`` to raise.
    """

    def _init_inbox(self) -> None:
        self.dropped: Counter = Counter()  # messages a full inbox refused, by kind
        self._inbox: queue.Queue = queue.Queue(maxsize=INBOX_MESSAGES)
        self._drop_lock = threading.Lock()
        self._scoring_error: Exception | None = None
        self._scorer: threading.Thread | None = None

    def _start_scorer(self) -> None:
        """The scorer thread, once what it scores into exists (messages queued before wait for it)."""
        self._scorer = threading.Thread(target=self._score_inbox, name="demo-scorer", daemon=True)
        self._scorer.start()

    def _end_scoring(self) -> None:
        """After the last message: the scorer drains the queue and ends (nothing to do if it never started)."""
        if self._scorer is not None:
            self._inbox.put(None)
            self._scorer.join()

    def _keep(self, kind: str, sample, *context) -> None:
        """Zenoh callback: enqueue the payload for the scorer; a full inbox drops it (counted)."""
        try:
            self._inbox.put_nowait((kind, *context, sample.payload.to_bytes()))
        except queue.Full:
            with self._drop_lock:
                self.dropped[kind] += 1

    def _watch_with_live_line(self, start_ns: int, events=lambda: (0, 0)) -> None:
        """``self._watch(start_ns)`` with the live line on stderr (``self.progress`` names it; None: no
        line); ``events()``: chaos events (played, planned)."""
        if self.progress:
            self._live = LiveLine(self.progress, start_ns, self.duration_s, events)
            self._live.start()
        try:
            self._watch(start_ns)
        finally:
            if self._live is not None:
                self._live.stop()

    def _score_inbox(self) -> None:
        """Scorer thread: decode and score each message in arrival order until the None that ends the run."""
        while (item := self._inbox.get()) is not None:
            if self._scoring_error is not None:
                continue  # keep draining so that the callbacks never block; run() raises it
            try:
                self._score(*item)
            except CodecError as exc:
                source = f" from {item[1]}" if len(item) > 2 else ""
                log("demo", f"undecodable {item[0]} message{source}: {exc}")
            except Exception as exc:  # noqa: BLE001 - re-raised by run() as a DemoError
                self._scoring_error = exc


def obu_own_count(record: RunRecord) -> dict | None:
    """The OBU's own count of its outputs (its last ``ObuMetrics``): cycles it published and how many
    of them missed their deadline; None when no metrics were heard. The report's
    ``output_deadline_miss_ratio`` counts expected cycles without an on-time output *heard by the
    monitor*: the two agree when the monitor hears every output (it subscribes before time zero)."""
    if record.obu_cycles is None:
        return None
    return {"cycles": record.obu_cycles, "misses": record.obu_output_deadline_misses,
            "ratio": round(record.obu_output_deadline_misses / max(record.obu_cycles, 1), 4)}


def startup_summary(ready_s: float | None, children) -> dict:
    """How the run started: launch -> every service ready (s), the start line's lead (s), and how
    many ms before time zero each service began (its ``started`` line; the emulator has none)."""
    return {"ready_s": None if ready_s is None else round(ready_s, 2), "lead_s": START_LEAD_S,
            "started_ahead_ms": {name: ms for name, ms in ahead_ms(children).items() if ms is not None}}
