"""The recorder of ``v2i record`` and ``v2i demo --record``: every ``v2x/**`` sample heard at one or
more endpoints, into an MCAP file.

One Zenoh session per endpoint, in *client* mode: a peer forwards what its other peers publish
to its clients (a Zenoh 1.x peer session would hear only the endpoint's own publications), and
separate sessions never bridge two endpoints (an RSU and an OBU side must stay apart: the link
emulator is the only path between them). Each endpoint is a *side* (``--connect rsu=tcp/...``;
default ``ep0``, ``ep1``, ...), and a sample is recorded on topic ``/<side>/<key>`` with its
receive time (``v2i.telemetry.mcap_writer``).

Time replies are not samples, so no subscriber hears the OBU's exchanges. To carry the RSU clock
into a recording, the recorder runs its own four-timestamp exchanges (``TimeRequest`` as querier
``recorder``, ``--sync-rate-hz``) on the ``--time-from`` side (default: the first; best the RSU
side, where they bypass the link and do not draw from its channel model) and records each reply
on ``/<side>/v2x/rsu/<id>/time``, log time = t4 (the reply carries t1, t2, t3). ``v2i replay``
rebuilds the RSU clock from them (``v2i.telemetry.time_shift.RsuClockTrack``). Host clocks: t1 and t4
are this host's wall clock; the replay is faithful where the recorded OBU ran on the same host
(``v2i demo``) or on one synchronised with it.

Zenoh callbacks only enqueue (bounded; a full queue drops, counted); one writer thread writes.
Ctrl-C / SIGTERM / ``--duration`` end it with the MCAP summary written. Crash-safe
(``v2i.telemetry.mcap_writer``): the writer thread writes the chunk in progress every ``FLUSH_S``, so
a recorder killed by SIGKILL leaves all but its last ~second in a file without summary, which
``v2i replay`` reads (and says it was not closed); a write that fails (a full disk) stops the
recording, the file cut back to its last whole chunk (exit 1). The signal handlers are set before
the file is opened, and a signal while the summary is written is acted on once it is written.
"""

from __future__ import annotations

import queue
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

QUEUE_ITEMS = 20_000
PROGRESS_S = 1.0
FLUSH_S = 1.0  # the chunk in progress is written at least this often (what a SIGKILL can lose)
RECORDER_ID = "recorder"
TIME_QUERY_TIMEOUT_S = 2.0


class Recorder:
    """Records from ``endpoints`` [(side, endpoint)] into ``out`` between ``start()`` and ``stop()``."""

    def __init__(self, endpoints: list[tuple[str, str]], out: str | Path, time_from: str | None = "",
                 sync_rate_hz: float = 10.0, metadata: dict[str, dict[str, str]] | None = None):
        from v2i.telemetry.mcap_writer import RunWriter

        if not endpoints:
            raise ValueError("v2i record needs at least one --connect endpoint")
        self.endpoints = endpoints
        self.time_from = endpoints[0][0] if time_from == "" else time_from
        if self.time_from is not None and self.time_from not in dict(endpoints):
            raise ValueError(f"--time-from {self.time_from}: no endpoint has that label")
        self.sync_period_s = 1.0 / sync_rate_hz
        self.path = Path(out)
        self.writer = RunWriter(out)
        self.failure: str | None = None  # why the file could not be written to the end
        for name, data in (metadata or {}).items():
            self.writer.add_metadata(name, data)
        self.dropped: Counter = Counter()
        self._queue: queue.Queue = queue.Queue(maxsize=QUEUE_ITEMS)
        self._stop = threading.Event()
        self._sessions, self._entities, self._threads = [], [], []
        self._seq = 0
        self.started_ns = 0

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        from v2i.runtime.transport import open_session

        self.started_ns = time.time_ns()
        self.writer.add_metadata("recording", {"started_ns": str(self.started_ns),
                                               "endpoints": ",".join(f"{s}={e}" for s, e in self.endpoints),
                                               "time_from": self.time_from or ""})
        for side, endpoint in self.endpoints:
            session = open_session(connect=[endpoint], mode="client")
            self._sessions.append((side, session))
            self._entities.append(session.declare_subscriber(
                "v2x/**", lambda sample, s=side: self._keep(s, str(sample.key_expr), sample.payload.to_bytes())))
        self._threads = [threading.Thread(target=self._write_loop, name="record-writer", daemon=True)]
        if self.time_from is not None:
            self._threads.append(threading.Thread(target=self._sync_loop, name="record-sync", daemon=True))
        for thread in self._threads:
            thread.start()

    def stop(self) -> None:
        """Stop hearing, write what is queued, write the summary (idempotent). A SIGINT / SIGTERM
        meanwhile is acted on when the file is finished (``_signals_deferred``)."""
        if self._stop.is_set():
            return
        self._stop.set()
        with _signals_deferred():
            for entity in self._entities:
                entity.undeclare()
            for _, session in self._sessions:
                session.close()
            self._queue.put(None)
            for thread in self._threads:
                thread.join()
            self._close_file()
        print(self.progress(final=True), file=sys.stderr, flush=True)

    def _close_file(self) -> None:
        try:
            self.writer.close()
        except OSError as exc:
            self._failed(exc)

    def run(self, stop: threading.Event, duration_s: float | None) -> None:
        """Record until ``stop`` is set, ``duration_s`` passed or a write failed, a progress line on
        stderr each second."""
        end = None if duration_s is None else time.monotonic() + duration_s
        self.start()
        try:
            while not stop.wait(PROGRESS_S if end is None else max(min(PROGRESS_S, end - time.monotonic()), 0)):
                print(self.progress(), file=sys.stderr, flush=True)
                if self.failure is not None or (end is not None and time.monotonic() >= end):
                    break
        finally:
            self.stop()

    def progress(self, final: bool = False) -> str:
        w = self.writer
        elapsed_s = (time.time_ns() - self.started_ns) * 1e-9
        skipped = f", derived skipped {dict(w.skipped)}" if w.skipped else ""
        dropped = f", dropped {dict(self.dropped)}" if self.dropped else ""
        head = "v2i record: wrote" if final else "v2i record:"
        line = f"{head} {w.messages} messages, {w.bytes / 1e6:.2f} MB, {elapsed_s:.1f} s{skipped}{dropped}"
        if final and self.failure is not None:
            line += (f"; NOT CLOSED: {self.failure} (the file keeps its first {w.file_bytes} bytes, up to the last "
                     "whole chunk, without a summary: v2i replay reads it)")
        return line

    # ------------------------------------------------------------------ threads and callbacks
    def _keep(self, side: str, key: str, payload: bytes) -> None:
        """Zenoh callback: stamp and enqueue (a full queue drops, counted)."""
        try:
            self._queue.put_nowait((side, key, payload, time.time_ns()))
        except queue.Full:
            self.dropped[side] += 1

    def _write_loop(self) -> None:
        """Write what is queued, the chunk in progress at least every ``FLUSH_S``, until None; after
        a failed write (``failure``) only drain the queue."""
        next_flush_s = time.monotonic() + FLUSH_S
        while True:
            try:
                item = self._queue.get(timeout=max(next_flush_s - time.monotonic(), 0.0))
            except queue.Empty:
                item = ()
            if item is None:
                return
            if self.failure is not None:  # keep draining, so that stop() can queue its None
                self.dropped["not_written"] += bool(item)
                continue
            try:
                if item:
                    self.writer.write(*item)
                if time.monotonic() >= next_flush_s:
                    self.writer.flush()
                    next_flush_s = time.monotonic() + FLUSH_S
            except OSError as exc:  # the file cannot take more (a full disk): cut back, stop recording
                self._failed(exc)
            except Exception as exc:  # noqa: BLE001 - one bad sample must not end the recording
                self.dropped[f"write_{type(exc).__name__}"] += 1

    def _failed(self, exc: OSError) -> None:
        if self.failure is None:
            self.failure = f"writing {self.path} failed ({exc.strerror or exc})"
            print(f"v2i record: {self.failure}; stopping", file=sys.stderr, flush=True)

    def _sync_loop(self) -> None:
        """A time request to every RSU on the ``time_from`` side each period; replies recorded."""
        import zenoh

        from schemas import keys
        from schemas.codec import encode
        from schemas.messages import TimeRequest

        session = dict(self._sessions)[self.time_from]
        while not self._stop.wait(self.sync_period_s):
            self._seq += 1
            request = TimeRequest(obu_id=RECORDER_ID, seq=self._seq, t1_ns=time.time_ns())
            try:
                session.get(keys.RSU_TIME_ALL, self._on_reply, payload=encode(request),
                            timeout=TIME_QUERY_TIMEOUT_S, consolidation=zenoh.ConsolidationMode.NONE)
            except zenoh.ZError:  # the session closed under us at stop
                return

    def _on_reply(self, reply) -> None:
        if reply.ok is not None:
            self._keep(self.time_from, str(reply.ok.key_expr), reply.ok.payload.to_bytes())


@contextmanager
def _signals_deferred() -> Iterator[None]:
    """In the main thread: SIGINT and SIGTERM that arrive inside are handled on the way out (the
    first of them, by the handler that was in force), not in the middle of writing the summary.
    Elsewhere (no handler can be set): nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[tuple[int, object]] = []
    previous = {sig: signal.signal(sig, lambda signum, frame: pending.append((signum, frame)))
                for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        if pending:
            signum, frame = pending[0]
            handler = previous[signum]
            if callable(handler):
                handler(signum, frame)  # e.g. KeyboardInterrupt (v2i demo), or stop.set (v2i record)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(signum)
