"""Bounded, rate-limited hand-over of received payloads from Zenoh callbacks to a service loop.

Zenoh callbacks (any thread) ``put``; the one loop that owns a service's state ``get``s.
``put`` never blocks and does O(1) work before anything is read or decoded (the payload is
copied out of Zenoh only once admitted), so a flood costs the flooder, not the service:

- a payload over ``max_bytes`` is refused unread (``too_large``);
- each source (the key expression it arrived on) has a token bucket: ``rate_hz`` sustained,
  ``burst`` at once; over it, ``rate_limited``. At most ``max_sources`` buckets are kept
  (the least recently used one is forgotten);
- except the *signed* kinds (``signed_kinds``: what the loop verifies before it reads anything).
  Before verification a forgery naming the genuine signer cannot be told from the genuine message,
  so a budget drawn by both would let a flood on the genuine key starve it. Their rate budget is
  taken after verification, per verified signer (``obu_service.inbound_security``), and here they
  only meet the *unverified* budget: a bucket per source (``unverified_rate_hz``, ``unverified_burst``)
  and one for all non-preferred sources together (``unverified_total_hz``), which only messages that
  failed verification draw from (``charge_unverified``, called by the loop after verifying). A
  verified RSU never spends it; it only runs dry under a flood of failures faster than the budget
  (what the OBU verifies on one core without missing cycles: docs/security.md), and then a
  signed message of that source is refused unread (``unverified_budget``), genuine or not. A signed
  kind's payload that fails a check needing no signature (``screen``: e.g. no envelope at all under
  a strict policy) is refused at once, counted under its reason; it cost no verification, so it
  draws nothing from that budget;
- the queue holds at most ``capacity`` items and ``max_queued_bytes``; beyond, the oldest
  item of the source with the most queued items is dropped (``queue_full``): the flooder
  loses its backlog, the others keep theirs.

``get`` serves sources round-robin, *preferred* sources (e.g. the site's registered RSUs)
before the others, so a flood on other keys cannot delay them. Every refusal is counted by
reason (``take_counts``); a refusal of a preferred source's message is also timed
(``crowded_ns``): genuine input may have been crowded out.
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
        self._refill(now_ns)
        if self._tokens < cost:
            return False
        self._tokens -= cost
        return True

    def has(self, now_ns: int) -> bool:
        """Whether one token is there now (none taken)."""
        self._refill(now_ns)
        return self._tokens >= 1.0

    def spend(self, now_ns: int, cost: float = 1.0) -> None:
        """Spend ``cost`` for an event that already passed: the balance may go negative, down to
        -burst (a debt the refill pays first)."""
        self._refill(now_ns)
        self._tokens = max(self._tokens - cost, -self.burst)

    def _refill(self, now_ns: int) -> None:
        self._tokens = min(self.burst, self._tokens + max(now_ns - self._last_ns, 0) * 1e-9 * self.rate_hz)
        self._last_ns = max(now_ns, self._last_ns)


class KeyedBuckets:
    """A token bucket per key (created full); only the ``max_keys`` most recently used are kept,
    so a flood of new keys costs memory for ``max_keys`` buckets at most. Not thread-safe."""

    def __init__(self, rate_hz: float, burst: int, max_keys: int = 1024):
        self.rate_hz, self.burst, self.max_keys = rate_hz, burst, max_keys
        self._buckets: OrderedDict[str, TokenBucket] = OrderedDict()

    def take(self, key: str, now_ns: int) -> bool:
        """One token of ``key``'s bucket, if it has one."""
        return self._bucket(key, now_ns).take(now_ns)

    def has(self, key: str, now_ns: int) -> bool:
        """Whether ``key``'s bucket holds a token (none taken); a key without a bucket has a full one."""
        bucket = self._buckets.get(key)
        return bucket is None or bucket.has(now_ns)

    def spend(self, key: str, now_ns: int) -> None:
        """One token of ``key``'s bucket spent after the fact (its balance may go down to -burst)."""
        self._bucket(key, now_ns).spend(now_ns)

    def _bucket(self, key: str, now_ns: int) -> TokenBucket:
        """``key``'s bucket (a full new one if it had none), now the most recently used."""
        bucket = self._buckets.get(key)
        if bucket is None:
            bucket = self._buckets[key] = TokenBucket(self.rate_hz, self.burst, now_ns)
            if len(self._buckets) > self.max_keys:
                self._buckets.popitem(last=False)
        self._buckets.move_to_end(key)
        return bucket


# The unverified budget (see the module docstring): failed verifications a source, and all non-preferred
# sources together, may cost per second. A forged signature costs the OBU ~75 us to refuse (P-256; a whole
# intake -> verify turn ~100 us), so 4000/s of them is ~30-40 % of one core at most: above any flood
# the acceptance measures (2000/s), below what would make cycles late.
UNVERIFIED_RATE_HZ = 4000.0
UNVERIFIED_BURST = 1000
UNVERIFIED_TOTAL_HZ = 4000.0


class Intake:
    def __init__(self, capacity: int = 512, max_bytes: int = 1 << 20, rate_hz: float = 50.0, burst: int = 25,
                 max_sources: int = 1024, max_queued_bytes: int = 32 << 20,
                 preferred: Callable[[str], bool] = lambda source: False,
                 clock_ns: Callable[[], int] = time.monotonic_ns, signed_kinds: frozenset[str] = frozenset(),
                 unverified_rate_hz: float = UNVERIFIED_RATE_HZ, unverified_burst: int = UNVERIFIED_BURST,
                 unverified_total_hz: float = UNVERIFIED_TOTAL_HZ,
                 screen: Callable[[bytes], str | None] = lambda payload: None):
        """``signed_kinds``: the kinds the loop verifies before reading (their budget: ``charge_unverified``
        here, the verified signer's after verification); the others are rate-limited per source here.
        ``screen(payload)``: a signed kind's refusal reason found without verifying (e.g. no envelope
        where one is required), or None; such a payload is refused here, never queued."""
        self.capacity, self.max_bytes, self.max_queued_bytes = capacity, max_bytes, max_queued_bytes
        self._preferred, self._clock_ns = preferred, clock_ns
        self._cond = threading.Condition()
        self._queues: dict[str, deque[Item]] = {}
        self._rings: tuple[OrderedDict[str, None], OrderedDict[str, None]] = (OrderedDict(), OrderedDict())
        self._buckets = KeyedBuckets(rate_hz, burst, max_sources)
        self._signed_kinds, self._screen = signed_kinds, screen
        self._unverified = KeyedBuckets(unverified_rate_hz, unverified_burst, max_sources)
        self._unverified_total = TokenBucket(unverified_total_hz, unverified_burst, clock_ns())
        self._counts: Counter[str] = Counter()
        self._items = self._bytes = 0
        self.crowded_ns: int | None = None  # the latest refusal of a preferred source's message (clock_ns)

    def __len__(self) -> int:
        return self._items

    def put(self, kind: str, source: str, size: int, receive_ns: int, read: Callable[[], bytes]) -> bool:
        """Queue one payload of ``size`` bytes, copied by ``read()`` only if admitted; False
        (and counted) when it is refused."""
        if size > self.max_bytes:
            return self._refuse("too_large", source)
        with self._cond:
            if kind in self._signed_kinds:
                refusal = None if self._unverified_left(source) else "unverified_budget"
            else:
                refusal = None if self._buckets.take(source, self._clock_ns()) else "rate_limited"
        if refusal is not None:
            return self._refuse(refusal, source)
        payload = read()
        if kind in self._signed_kinds and (reason := self._screen(payload)) is not None:
            with self._cond:  # refused here as the loop would, at no verification cost (nothing charged)
                self._counts[reason] += 1
            return False
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

    def charge_unverified(self, source: str) -> None:
        """A message of ``source`` failed verification: one token of the unverified budget spent (the
        source's, and the shared one unless the source is preferred)."""
        with self._cond:
            now_ns = self._clock_ns()
            self._unverified.spend(source, now_ns)
            if not self._preferred(source):
                self._unverified_total.spend(now_ns)

    def crowded_within(self, window_ns: int) -> bool:
        """Whether a preferred source's message was refused in the last ``window_ns``."""
        crowded_ns = self.crowded_ns
        return crowded_ns is not None and self._clock_ns() - crowded_ns <= window_ns

    def take_counts(self) -> Counter[str]:
        """Refusals by reason since the last call."""
        with self._cond:
            counts, self._counts = self._counts, Counter()
        return counts

    # --- internals (under the lock) ---------------------------------------------------------
    def _refuse(self, reason: str, source: str) -> bool:
        with self._cond:
            self._counts[reason] += 1
            if self._preferred(source):
                self.crowded_ns = self._clock_ns()
        return False

    def _unverified_left(self, source: str) -> bool:
        """Whether a signed message of ``source`` may still be verified: its unverified budget, and the
        shared one unless the source is preferred (a flood on other keys never takes a registered RSU's)."""
        now_ns = self._clock_ns()
        return self._unverified.has(source, now_ns) and (self._preferred(source) or self._unverified_total.has(now_ns))

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
        if ring is self._rings[0]:
            self.crowded_ns = self._clock_ns()
