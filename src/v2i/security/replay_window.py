"""Replay detection per signer, bounded in memory.

A message is identified by ``(generation_ns, payload hash)`` under its signer's certificate
digest. Per signer we keep the ids seen whose ``generation_ns`` lies within ``window_ns`` of the
newest ``generation_ns`` that signer has used (its own clock: no clock offset enters), plus a
floor below which nothing can be proven new:

    floor = max(newest - window_ns, generation_ns of the newest id evicted for capacity)

``check_and_add`` answers ``"ok"`` (new: remembered), ``"replayed"`` (seen) or ``"stale"`` (at
or below the floor). Memory is bounded by ``per_signer`` ids per signer and ``max_signers``
signers (least recently used signer dropped: its next message starts afresh, still subject to
the verifier's freshness check). Only messages whose signature verified are ever added, so an
attacker without a key cannot fill it.
"""

from __future__ import annotations

import heapq
from collections import OrderedDict


class _Signer:
    __slots__ = ("seen", "heap", "newest_ns", "floor_ns")

    def __init__(self) -> None:
        self.seen: set[tuple[int, bytes]] = set()
        self.heap: list[tuple[int, bytes]] = []  # min-heap of (generation_ns, payload hash)
        self.newest_ns = -1
        self.floor_ns = -1


class ReplayWindow:
    """Seen-message memory; ``window_ns`` >= the verifier's freshness window."""

    def __init__(self, window_ns: int, per_signer: int = 4096, max_signers: int = 1024) -> None:
        if window_ns <= 0 or per_signer <= 0 or max_signers <= 0:
            raise ValueError("window_ns, per_signer and max_signers must be positive")
        self.window_ns = window_ns
        self.per_signer = per_signer
        self.max_signers = max_signers
        self._signers: OrderedDict[bytes, _Signer] = OrderedDict()

    def __len__(self) -> int:
        return sum(len(s.seen) for s in self._signers.values())

    def _signer(self, digest: bytes) -> _Signer:
        state = self._signers.get(digest)
        if state is None:
            state = self._signers[digest] = _Signer()
            if len(self._signers) > self.max_signers:
                self._signers.popitem(last=False)
        else:
            self._signers.move_to_end(digest)
        return state

    def _expire(self, state: _Signer) -> None:
        """Forget ids at or below the floor (they are rejected as stale from now on)."""
        state.floor_ns = max(state.floor_ns, state.newest_ns - self.window_ns)
        while state.heap and state.heap[0][0] <= state.floor_ns:
            state.seen.discard(heapq.heappop(state.heap))
        while len(state.heap) > self.per_signer:
            evicted = heapq.heappop(state.heap)
            state.seen.discard(evicted)
            state.floor_ns = max(state.floor_ns, evicted[0])

    def check_and_add(self, digest: bytes, generation_ns: int, payload_hash: bytes) -> str:
        """``"ok"`` and remember, ``"replayed"`` if seen, ``"stale"`` if at or below the floor."""
        state = self._signer(digest)
        ident = (generation_ns, payload_hash)
        if generation_ns <= state.floor_ns:
            return "stale"
        if ident in state.seen:
            return "replayed"
        state.seen.add(ident)
        heapq.heappush(state.heap, ident)
        state.newest_ns = max(state.newest_ns, generation_ns)
        self._expire(state)
        return "ok" if ident in state.seen else "stale"
