"""One answer per time query (pure): an RSU answers a (querier, request id, t1) once.

A query can reach the RSU more than once: the link duplicates it, or someone who heard it
forwards it later. Two answers to one query are two genuine, signed replies with different t2 /
t3; an OBU that voided both (``v2i.clock.time_requests``) let a relay stop its clock (issue 32).
The key includes the OBU's t1 (ns), which nobody can guess ahead, so that queries forged ahead
with a victim's id and future sequence numbers cannot use up its answers. Memory is bounded:
the oldest keys are forgotten first (a later repeat of one is answered again, and the OBU keeps
the first valid reply of a request anyway).
"""

from __future__ import annotations

from collections import OrderedDict

from schemas.messages import TimeRequest

MAX_REMEMBERED = 4096  # queries remembered: 10 Hz x 64 vehicles x 6 s


class TimeAnswers:
    def __init__(self, capacity: int = MAX_REMEMBERED):
        self.capacity = capacity
        self._seen: OrderedDict[tuple[str, int, int], None] = OrderedDict()

    def first(self, request: TimeRequest) -> bool:
        """Whether this query is new (it is remembered now); False for a repeat (not to be answered)."""
        key = (request.obu_id, request.seq, request.t1_ns)
        if key in self._seen:
            return False
        self._seen[key] = None
        if len(self._seen) > self.capacity:
            self._seen.popitem(last=False)
        return True
