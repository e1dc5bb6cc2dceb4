"""Timed events in due order (pure: no clock, no thread; imports nothing of the project).

The one scheduler of every loop that fires timed events: the OBU node's loop (``obu_service.node``),
the offline runner's event queue (``v2i.offline.runner``), the world feed (``v2i.world_feed``) and the
link relay's action queue (``link_emulator.scheduler``, which adds a lock and the sleeping around it).

Order: the due time (ns), then ``rank`` (a small int the caller gives: which of two events due at the
same time fires first; 0 by default), then push order. A binary heap (``heapq``) of
``(due_ns, rank, seq, event)``: push and pop O(log n), the head O(1); ``seq`` is unique, so two
entries never tie and an event itself is never compared.
"""

from __future__ import annotations

import heapq
import itertools
from typing import Generic, TypeVar

E = TypeVar("E")


class Timeline(Generic[E]):
    """Events by due time (see the module docstring); empty is falsy."""

    def __init__(self) -> None:
        self._heap: list[tuple[int, int, int, E]] = []
        self._seq = itertools.count()

    def push(self, due_ns: int, event: E, rank: int = 0) -> None:
        """``event`` due at ``due_ns``; among those due then, after lower ranks and those pushed before."""
        heapq.heappush(self._heap, (due_ns, rank, next(self._seq), event))

    def head(self) -> tuple[int, E]:
        """(due_ns, event) of the next event, left in place; IndexError when empty."""
        due_ns, _, _, event = self._heap[0]
        return due_ns, event

    def pop(self) -> tuple[int, E]:
        """(due_ns, event) of the next event, taken out; IndexError when empty."""
        due_ns, _, _, event = heapq.heappop(self._heap)
        return due_ns, event

    def clear(self) -> int:
        """Forget every event; how many there were."""
        pending = len(self._heap)
        self._heap.clear()
        return pending

    def __len__(self) -> int:
        return len(self._heap)
