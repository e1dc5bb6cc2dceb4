"""A timed action queue: any thread pushes ``(due_ns, action)``, one thread fires them on time.

The order is ``v2i.core.scheduler.Timeline``'s (due time, then push order); this module adds the
lock, the condition variable and the sleeping.

The link relay's timing accuracy is this module's (see ``benchmarks/relay_accuracy.py``):

- The firing thread sleeps on a condition variable until the head is due; a push whose
  action becomes the new head wakes it, so a short delay is never stuck behind a long sleep.
- A timed sleep wakes late by the kernel's timer slack (50 us by default on Linux) plus the
  thread's wake-up. So the thread sleeps only until ``spin_ns`` before the due time and then
  polls the clock, yielding the GIL between polls so that Zenoh callbacks are not held up;
  on Linux it also asks for a 1 us timer slack for its own sleeps.
- The firing time is read once, right before the action; actions do their I/O first.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import sys
import threading
import time
from collections.abc import Callable

from v2i.core.clock import Clock
from v2i.core.scheduler import Timeline

log = logging.getLogger(__name__)

Action = Callable[[int], None]  # called with the firing time in ns

MAX_WAIT_S = 0.05  # longest sleep, i.e. the latency of noticing ``stop``
# The last 60 us before a due time are polled, not slept: a Python thread woken from a timed
# wait runs 40-90 us late here (benchmarks/relay_accuracy.py: lateness p50 0.09 ms without
# polling, 0.045 ms with the timer slack alone, 0.012 ms with both). Polling 0.2 ms gained
# nothing more but took CPU from the Zenoh threads on 2 cores, lengthening both hops.
SPIN_NS = 60_000
PR_SET_TIMERSLACK = 29  # linux/prctl.h
TIMER_SLACK_NS = 1_000


def reduce_timer_slack(slack_ns: int = TIMER_SLACK_NS) -> bool:
    """Ask Linux to wake this thread's timed sleeps within ``slack_ns``; False where unsupported."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        return libc.prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(slack_ns), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


class EventScheduler:
    """Actions on a ``Timeline``: any thread pushes, one thread (``run``) fires them in due order."""

    def __init__(self, clock: Clock, max_wait_s: float = MAX_WAIT_S, spin_ns: int = SPIN_NS) -> None:
        self._clock = clock
        self._max_wait_s = max_wait_s
        self._spin_ns = spin_ns
        self._timeline: Timeline[Action] = Timeline()
        self._cond = threading.Condition()

    def push(self, due_ns: int, action: Action) -> None:
        """Schedule ``action(fired_ns)`` at ``due_ns`` (clock ns); thread-safe."""
        with self._cond:
            self._timeline.push(due_ns, action)
            if self._timeline.head()[1] is action:
                self._cond.notify()  # a new head: the sleeper must re-compute its wake-up time

    def run(self, stop: threading.Event) -> None:
        """Fire due actions until ``stop`` is set; an action's exception is logged, not fatal."""
        reduce_timer_slack()
        while not stop.is_set():
            action = self._next_due()
            if action is None:
                continue
            try:
                action(self._clock.now_ns())
            except Exception:
                log.exception("scheduled action failed")

    def clear(self) -> int:
        """Forget every pending action; returns how many there were."""
        with self._cond:
            return self._timeline.clear()

    def _next_due(self) -> Action | None:
        """The head action once it is due, or None after a sleep (at most ``max_wait_s``)."""
        with self._cond:
            if not self._timeline:
                self._cond.wait(self._max_wait_s)
                return None
            due_ns, _ = self._timeline.head()
            sleep_ns = due_ns - self._spin_ns - self._clock.now_ns()
            if sleep_ns > 0:
                self._cond.wait(min(sleep_ns / 1e9, self._max_wait_s))
                return None
        self._spin_until(due_ns)
        with self._cond:
            # The head is due: it is the one polled for, or an even earlier one pushed meanwhile.
            return self._timeline.pop()[1] if self._timeline else None

    def _spin_until(self, due_ns: int) -> None:
        """Poll until ``due_ns``, outside the lock; sleep(0) lets other threads take the GIL.

        Polls the monotonic clock so that a step of the wall clock cannot prolong the spin.
        """
        remaining_ns = min(due_ns - self._clock.now_ns(), self._spin_ns)
        end_ns = time.perf_counter_ns() + remaining_ns
        while time.perf_counter_ns() < end_ns:
            time.sleep(0)
