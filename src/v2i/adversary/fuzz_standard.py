"""Hostile CPM / SDSM object lists for the fuzz command (pure, seeded): RSU lists in the standard
encodings (``schemas.cpm``, ``schemas.sdsm``; RSU ``--wire cpm|sdsm``) broken every way UPER
bytes break. ``StandardHostile(rng).make(wire, t_ns)`` gives one payload of a random kind
(``STANDARD_KINDS``); the live driver (``v2i.adversary.fuzz_targets``) publishes it on the RSU keys
``v2x/rsu/<id>/cpm`` / ``.../sdsm``, where the OBU must only ever count a rejection.
"""

from __future__ import annotations

import numpy as np

from schemas import cpm, sdsm
from schemas import standard_wire as sw
from schemas.messages import ObjectListHeader

MS = 1_000_000
STANDARD_KINDS = ("random_bytes", "truncated", "bit_flips", "byte_storm", "absurd_time", "valid")
WIRES = {"cpm": cpm, "sdsm": sdsm}


class StandardHostile:
    """Hostile payloads around a valid CPM or SDSM of ``n_objects`` objects (map frame) at ``t_ns``."""

    def __init__(self, rng: np.random.Generator, rsu_id: str = "rsu1", origin: tuple[float, float] | None = None):
        """``origin``: the target's site origin (WGS84 lat, lon degrees), a valid CPM's reference position,
        so that its objects land in the target's map (None: 0 N 0 E, thousands of km from any site)."""
        self.rng, self.rsu_id, self.origin = rng, rsu_id, origin

    def valid(self, wire: str, t_ns: int, n_objects: int = 8, capture_ns: int | None = None) -> bytes:
        n = n_objects
        cols = sw.empty_columns(n)
        cols.update(id=np.arange(n, dtype=float), x=self.rng.uniform(-80, 80, n), y=self.rng.uniform(-80, 80, n),
                    length=np.full(n, 4.5), width=np.full(n, 1.8), yaw=self.rng.uniform(-3, 3, n),
                    vx=self.rng.uniform(-20, 20, n), vy=self.rng.uniform(-20, 20, n),
                    cov_vxx=np.full(n, 0.1), cov_vyy=np.full(n, 0.1), cls=self.rng.integers(0, 8, n).astype(float))
        capture = t_ns - 150 * MS if capture_ns is None else capture_ns
        header = ObjectListHeader(rsu_id=self.rsu_id, seq=int(self.rng.integers(1 << 40)), capture_time_ns=capture,
                                  publish_time_ns=capture + 100 * MS)
        return cpm.encode(header, cols, origin=self.origin) if wire == "cpm" else WIRES[wire].encode(header, cols)

    def make(self, wire: str, t_ns: int) -> tuple[str, bytes]:
        """(kind, payload): one hostile ``wire`` message of a random kind."""
        kind = STANDARD_KINDS[int(self.rng.integers(len(STANDARD_KINDS)))]
        return kind, getattr(self, f"_{kind}")(wire, t_ns)

    def _random_bytes(self, wire: str, t_ns: int) -> bytes:
        return self.rng.bytes(int(self.rng.integers(0, 2048)))

    def _truncated(self, wire: str, t_ns: int) -> bytes:
        data = self.valid(wire, t_ns)
        return data[: int(self.rng.integers(0, len(data)))]

    def _bit_flips(self, wire: str, t_ns: int) -> bytes:
        data = bytearray(self.valid(wire, t_ns))
        for i in self.rng.integers(0, len(data), int(self.rng.integers(1, 8))):
            data[i] ^= 1 << int(self.rng.integers(8))
        return bytes(data)

    def _byte_storm(self, wire: str, t_ns: int) -> bytes:
        """A valid prefix (header and first objects) followed by random bytes: lengths and counts lie."""
        data = self.valid(wire, t_ns, n_objects=int(self.rng.integers(1, 60)))
        cut = int(self.rng.integers(1, len(data)))
        return data[:cut] + self.rng.bytes(int(self.rng.integers(1, 4096)))

    def _absurd_time(self, wire: str, t_ns: int) -> bytes:
        """Well-formed, stamped an hour off (stale or from the future): the OBU's screen refuses it."""
        return self.valid(wire, t_ns, capture_ns=t_ns + int(self.rng.choice([-1, 1])) * 3_600_000 * MS)

    def _valid(self, wire: str, t_ns: int) -> bytes:
        return self.valid(wire, t_ns)
