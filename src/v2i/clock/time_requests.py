"""The OBU's outstanding NTP-style time requests and the replies they got (pure).

A request goes to every RSU (``v2x/rsu/*/time``), so each RSU may answer it once. A reply
is matched by ``seq`` and the echoed ``t1``. It is then *held* for ``hold_ns`` before it
reaches the clock filter (``ripe``); a repeated identical reply is a duplicate.

- A *verified* reply (its signature checked against the site's trust: ``match(...,
  verified=True)``) is the RSU's own reading, even when someone relayed it: the first one to a
  request counts, later different ones from the same RSU are ignored (``time_reply_later``),
  never voided. (A relay that got the RSU to answer a copy of the query can only add delay: the
  clock filter's envelope discounts a longer round trip, and a step needs evidence queueing
  cannot explain.) Voiding both let a relay that doubled every genuine reply stop the clock.
- An unverified reply (no PKI, or a permissive one that failed): a second, different reply from
  the same RSU id for the same request within ``hold_ns`` is a conflict (one of the two is
  forged, and which is unknown), so both are discarded. A forger that answers first therefore
  cannot push its reply in ahead of the genuine one; one that answers later than ``hold_ns``
  after the genuine reply is refused as a conflict; a forger the genuine RSU never contradicts
  in time is left to the clock filter's outlier test. A verified reply after an unverified one
  takes its place. Requests stay matchable for
``keep_ns`` (replies over a buffering cellular link can take tens of seconds), at most
``capacity`` are kept.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass, field

import numpy as np

from schemas.messages import TimeReply, TimeRequest

from v2i.clock.clock_sync import SyncSample


@dataclass
class _Reply:
    t2_ns: int
    t3_ns: int
    t4_ns: int
    conflicted: bool = False
    verified: bool = False
    used: bool = False  # handed to the clock filter


@dataclass
class _Pending:
    t1_ns: int
    replies: dict[str, _Reply] = field(default_factory=dict)  # rsu id -> its reply


class TimeRequests:
    def __init__(self, obu_id: str, keep_ns: int = 60_000_000_000, capacity: int = 1024,
                 hold_ns: int = 150_000_000):
        self.obu_id, self.keep_ns, self.capacity, self.hold_ns = obu_id, keep_ns, capacity, hold_ns
        self._pending: OrderedDict[int, _Pending] = OrderedDict()
        self._held: deque[tuple[int, int, str]] = deque()  # (t4, seq, rsu id) in arrival order
        self._seq = 0

    def __len__(self) -> int:
        return len(self._pending)

    def make(self, t1_ns: int) -> TimeRequest:
        """A request to send now (t1 = OBU send time); forgets requests older than keep_ns."""
        self._seq += 1
        self._pending[self._seq] = _Pending(t1_ns)
        while self._pending and (len(self._pending) > self.capacity
                                 or t1_ns - next(iter(self._pending.values())).t1_ns > self.keep_ns):
            self._pending.popitem(last=False)
        return TimeRequest(obu_id=self.obu_id, seq=self._seq, t1_ns=t1_ns)

    def match(self, reply: TimeReply, t4_ns: int, verified: bool = False) -> str | None:
        """Hold a reply for ``ripe``; or why it is refused: ``time_reply_unmatched`` (no such
        request), ``time_reply_duplicate``, ``time_reply_later`` (a verified reply came first),
        ``time_reply_conflict`` (two unverified ones: both are dropped)."""
        pending = self._pending.get(reply.seq)
        if pending is None or pending.t1_ns != reply.t1_ns:
            return "time_reply_unmatched"
        before = pending.replies.get(reply.rsu_id)
        if before is not None:
            if (before.t2_ns, before.t3_ns) == (reply.t2_ns, reply.t3_ns):
                return "time_reply_duplicate"
            if before.verified:
                return "time_reply_later"
            if not verified:
                before.conflicted = True
                return "time_reply_conflict"
            # a verified reply replaces an unverified one (which then never ripens: see ripe)
        pending.replies[reply.rsu_id] = _Reply(reply.t2_ns, reply.t3_ns, t4_ns, verified=verified)
        self._held.append((t4_ns, reply.seq, reply.rsu_id))
        return None

    def ripe(self, now_ns: int) -> list[tuple[str, SyncSample]]:
        """(rsu id, exchange) of the held replies older than hold_ns that no conflict voided."""
        out = []
        while self._held and now_ns - self._held[0][0] >= self.hold_ns:
            t4_ns, seq, rsu_id = self._held.popleft()
            pending = self._pending.get(seq)
            reply = None if pending is None else pending.replies[rsu_id]
            if reply is not None and reply.t4_ns == t4_ns and not (reply.conflicted or reply.used):  # (not replaced)
                reply.used = True
                out.append((rsu_id, SyncSample(pending.t1_ns, reply.t2_ns, reply.t3_ns, reply.t4_ns)))
        return out


SYNC_LEAD_NS = 1_000_000_000  # queries start this long before a run (a reply is held 150 ms first)


def sync_times_ns(now_ns: int, start_ns: int, duration_s: float, rate_hz: float) -> list[int]:
    """Times (ns) of a run's time queries: every 1 / ``rate_hz`` from ``SYNC_LEAD_NS`` (at least
    two periods) before the run's start, so that the clock is synchronised when it begins (two
    periods were not enough: with the 150 ms hold the first RSU frame often found no estimate),
    none in the past, until its end."""
    period_ns = round(1e9 / rate_hz)
    first_ns = max(now_ns, start_ns - max(2 * period_ns, SYNC_LEAD_NS))
    return [int(t) for t in np.arange(first_ns, start_ns + duration_s * 1e9, period_ns)]
