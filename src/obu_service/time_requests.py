"""The OBU's outstanding NTP-style time requests and the replies they got (pure).

A request goes to every RSU (``v2x/rsu/*/time``), so each RSU may answer it once. A reply
is matched by ``seq`` and the echoed ``t1``; a repeated identical reply is a duplicate, a
different second reply from the same RSU id a conflict (one of the two is forged): the second
is refused and counted by the caller (should the forged one have come first, the clock
filter's outlier test is what keeps it out of the estimate). Requests stay matchable
for ``keep_ns`` (replies over a buffering cellular link can take tens of seconds) and at
most ``capacity`` are kept.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

from schemas.messages import TimeReply, TimeRequest

from .clock_sync import SyncSample


@dataclass
class _Pending:
    t1_ns: int
    replies: dict[str, tuple[int, int]] = field(default_factory=dict)  # rsu id -> (t2, t3)


class TimeRequests:
    def __init__(self, obu_id: str, keep_ns: int = 60_000_000_000, capacity: int = 1024):
        self.obu_id, self.keep_ns, self.capacity = obu_id, keep_ns, capacity
        self._pending: OrderedDict[int, _Pending] = OrderedDict()
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

    def match(self, reply: TimeReply, t4_ns: int) -> SyncSample | str:
        """The exchange a reply completes, or why it is refused: ``time_reply_unmatched``
        (no such request), ``time_reply_duplicate`` or ``time_reply_conflict``."""
        pending = self._pending.get(reply.seq)
        if pending is None or pending.t1_ns != reply.t1_ns:
            return "time_reply_unmatched"
        before = pending.replies.get(reply.rsu_id)
        if before is not None:
            return "time_reply_duplicate" if before == (reply.t2_ns, reply.t3_ns) else "time_reply_conflict"
        pending.replies[reply.rsu_id] = (reply.t2_ns, reply.t3_ns)
        return SyncSample(pending.t1_ns, reply.t2_ns, reply.t3_ns, t4_ns)
