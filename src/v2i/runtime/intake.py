"""Bounded, rate-limited hand-over of received payloads from Zenoh callbacks to a service loop.

Zenoh callbacks (any thread) ``put``; the one loop that owns a service's state ``get``s.
``put`` never blocks and does O(1) work before anything is read or decoded (the payload is
copied out of Zenoh only once admitted), so a flood costs the flooder, not the service:

- a payload over ``max_bytes`` is refused unread (``too_large``);
- each source (the key expression it arrived on) has a token bucket: ``rate_hz`` sustained,
  ``burst`` at once; over it, ``rate_limited``. At most ``max_sources`` buckets are kept
  (the least recently used one is forgotten);
- the queue holds at most ``capacity`` items and ``max_queued_bytes``; beyond, the oldest
  item of the source with the most queued items is dropped (``queue_full``): the flooder
  loses its backlog, the others keep theirs.

``get`` serves sources round-robin, *preferred* sources (e.g. the site's registered RSUs)
before the others, so a flood on other keys cannot delay them. Every refusal is counted by
reason (``take_counts``).
"""

from __future__ import annotations

import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Item:
    kind: str  # what the loop should do with it, e.g. "rsu", "predictions", "time"
    source: str  # key expression it arrived on
    payload: bytes
    receive_ns: int


class TokenBucket:
    """``rate_hz`` tokens per second sustained, ``burst`` at once: tokens += rate dt (at most
    burst), one token per event (or its cost, e.g. its bytes). Not thread-safe: callers hold
    their own lock."""

    def __init__(self, rate_hz: float, burst: int, now_ns: int):
        self.rate_hz, self.burst = rate_hz, float(burst)
        self._tokens, self._last_ns = float(burst), now_ns

    def take(self, now_ns: int, cost: float = 1.0) -> bool:
        """True (and ``cost`` tokens spent) if an event of that cost may pass at ``now_ns``."""
        self._tokens = min(self.burst, self._tokens + max(now_ns - self._last_ns, 0) * 1e-9 * self.rate_hz)
        self._last_ns = now_ns
        if self._tokens < cost:
            return False
        self._tokens -= cost
        return True


class KeyedBuckets:
    """A token bucket per key (created full); only the ``max_keys`` most recently used are kept,
    so a flood of new keys costs memory for ``max_keys`` buckets at most. Not thread-safe."""

    def __init__(self, rate_hz: float, burst: int, max_keys: int = 1024):
        self.rate_hz, self.burst, self.max_keys = rate_hz, burst, max_keys
        self._buckets: OrderedDict[str, TokenBucket] = OrderedDict()

    def take(self, key: str, now_ns: int) -> bool:
        """One token of ``key``'s bucket, if it has one."""
        bucket = self._buckets.get(key)
        if bucket is None:
            bucket = self._buckets[key] = TokenBucket(self.rate_hz, self.burst, now_ns)
            if len(self._buckets) > self.max_keys:
                self._buckets.popitem(last=False)
        self._buckets.move_to_end(key)
        return bucket.take(now_ns)


class Intake:
    def __init__(self, capacity: int = 512, max_bytes: int = 1 << 20, rate_hz: float = 50.0, burst: int = 25,
                 max_sources: int = 1024, max_queued_bytes: int = 32 << 20,
                 preferred: Callable[[str], bool] = lambda source: False,
                 clock_ns: Callable[[], int] = time.monotonic_ns):
        self.capacity, self.max_bytes, self.max_queued_bytes = capacity, max_bytes, max_queued_bytes
        self._preferred, self._clock_ns = preferred, clock_ns
        self._cond = threading.Condition()
        self._queues: dict[str, deque[Item]] = {}
        self._rings: tuple[OrderedDict[str, None], OrderedDict[str, None]] = (OrderedDict(), OrderedDict())
        self._buckets = KeyedBuckets(rate_hz, burst, max_sources)
        self._counts: Counter[str] = Counter()
        self._items = self._bytes = 0

    def __len__(self) -> int:
        return self._items

    def put(self, kind: str, source: str, size: int, receive_ns: int, read: Callable[[], bytes]) -> bool:
        """Queue one payload of ``size`` bytes, copied by ``read()`` only if admitted; False
        (and counted) when it is refused."""
        if size > self.max_bytes:
            return self._refuse("too_large")
        with self._cond:
            if not self._buckets.take(source, self._clock_ns()):
                self._counts["rate_limited"] += 1
                return False
        payload = read()
        with self._cond:
            queue = self._queues.setdefault(source, deque())
            queue.append(Item(kind, source, payload, receive_ns))
            self._items, self._bytes = self._items + 1, self._bytes + len(payload)
            self._rings[0 if self._preferred(source) else 1][source] = None
            while self._items > self.capacity or self._bytes > self.max_queued_bytes:
                self._drop_oldest_of_largest()
            self._cond.notify()
        return True

    def get(self, timeout_s: float) -> Item | None:
        """The next item (preferred sources first, round-robin), or None after ``timeout_s``."""
        with self._cond:
            if not self._items:
                self._cond.wait(max(timeout_s, 0.0))
            ring = next((r for r in self._rings if r), None)
            if ring is None:
                return None
            source = next(iter(ring))
            return self._pop(source, ring)

    def take_counts(self) -> Counter[str]:
        """Refusals by reason since the last call."""
        with self._cond:
            counts, self._counts = self._counts, Counter()
        return counts

    # --- internals (under the lock) ---------------------------------------------------------
    def _refuse(self, reason: str) -> bool:
        with self._cond:
            self._counts[reason] += 1
        return False

    def _pop(self, source: str, ring: OrderedDict[str, None]) -> Item:
        """The oldest item of ``source``; the source goes to the back of its ring (round-robin)."""
        queue = self._queues[source]
        item = queue.popleft()
        self._items, self._bytes = self._items - 1, self._bytes - len(item.payload)
        del ring[source]
        if queue:
            ring[source] = None
        else:
            del self._queues[source]
        return item

    def _drop_oldest_of_largest(self) -> None:
        source = max(self._queues, key=lambda s: (not self._preferred(s), len(self._queues[s])))
        ring = self._rings[0] if source in self._rings[0] else self._rings[1]
        self._pop(source, ring)
        self._counts["queue_full"] += 1
