"""``IdentityMemo``: what a function gives for the objects last asked about, matched by identity.

Used where the same immutable object is asked about again and again: a scenario's bodies (every
view of one scenario), a world's building polygons (every frame), a decoded message (every
vehicle that hears one broadcast in the offline runner). The memo holds each object it answers
for, so the object's ``id`` cannot be reused while its entry is kept; past ``capacity`` entries it
forgets the entry it made first (a broadcast's receivers all ask within a short while: starting
afresh made the last receivers of the messages still in flight compute theirs again). Results are shared by whoever asks: return immutable ones (read-only arrays).
"""

from __future__ import annotations

from typing import Callable, Generic, TypeVar

K, V = TypeVar("K"), TypeVar("V")


class IdentityMemo(Generic[K, V]):
    """``function(obj)``, computed once per object (``is``, not ``==``) among the last ``capacity`` asked about."""

    def __init__(self, function: Callable[[K], V], capacity: int = 16):
        self._function, self._capacity = function, capacity
        self._kept: dict[int, tuple[K, V]] = {}  # id(obj) -> (obj, result): obj held, so its id stays its own

    def __call__(self, obj: K) -> V:
        kept = self._kept.get(id(obj))
        if kept is None:
            if len(self._kept) >= self._capacity:
                del self._kept[next(iter(self._kept))]  # the oldest entry (a dict keeps insertion order)
            kept = self._kept[id(obj)] = (obj, self._function(obj))
        return kept[1]
