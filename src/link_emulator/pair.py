"""One RSU-vehicle pair of the link emulator: its channel, the vehicle's position, its counters.

An emulator serves one RSU and up to ``config.MAX_VEHICLES`` vehicles; each vehicle has its
own ``VehiclePair``: its own ``LinkModel`` (own seeded draws, ``pair_seed``), its own
distance (its poses against the RSU position), its own in-flight caps, open time queries and
stats. Pure bookkeeping: the relay (``relay.py``) owns the Zenoh sessions and the clock.
"""

from __future__ import annotations

import hashlib
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from schemas.messages import LinkControl

from link_emulator.channel import LinkModel
from link_emulator.config import VehicleSide
from link_emulator.control import apply_control
from link_emulator.gate import InFlight, VehiclePosition
from link_emulator.profile import LinkProfile
from link_emulator.stats import DirectionStats, RunningStats

DIRECTIONS = ("uplink", "downlink")


@dataclass(frozen=True)
class Delivery:
    """One relayed message, reported to an observer right after it was sent on.

    ``due_ns - receive_ns`` is the drawn link delay; ``fired_ns - due_ns`` the relay's lateness.
    ``vehicle_id``: the pair's vehicle (None while the one-vehicle form has heard none).
    """

    direction: str  # "downlink" or "uplink"
    key: str
    payload: bytes | None
    receive_ns: int
    due_ns: int
    fired_ns: int
    vehicle_id: str | None = None


def pair_seed(seed: int, vehicle_id: str) -> int:
    """Seed of one vehicle's channel: a 128-bit hash of (seed, vehicle id).

    Depends on the vehicle's id only, not on how many vehicles there are or their order, so
    a vehicle keeps its draws when others join; distinct ids give independent streams.
    """
    digest = hashlib.sha256(f"v2i-link-pair/{seed}/{vehicle_id}".encode()).digest()
    return int.from_bytes(digest[:16], "big")


@dataclass
class VehiclePair:
    """The channel and counters of one RSU-vehicle pair (scheduler thread only).

    ``side.vehicle_id`` None (the one-vehicle form without ``--vehicle-id``): the pair is the
    first vehicle whose pose is heard. ``queries`` maps a forwarded query's id to the relay's
    record of it.
    """

    side: VehicleSide
    model: LinkModel
    position: VehiclePosition
    uplink: DirectionStats = field(default_factory=DirectionStats)
    downlink: DirectionStats = field(default_factory=DirectionStats)
    in_flight: dict[str, InFlight] = field(default_factory=lambda: {d: InFlight() for d in DIRECTIONS})
    queries: dict[int, Any] = field(default_factory=dict)

    @classmethod
    def create(cls, side: VehicleSide, profile: LinkProfile, seed: int, one_vehicle_form: bool) -> VehiclePair:
        """A pair for ``side``; the one-vehicle form keeps ``seed`` itself (today's draws), the
        many-vehicle form seeds each pair by ``pair_seed(seed, vehicle_id)``."""
        pair_seed_ = seed if one_vehicle_form else pair_seed(seed, side.vehicle_id)
        return cls(side, LinkModel(profile, pair_seed_), VehiclePosition(side.vehicle_id))

    @property
    def vehicle_id(self) -> str | None:
        """The configured id, else the first one heard, else None."""
        return self.side.vehicle_id or self.position.vehicle_id

    def gate_key(self, key: str) -> str:
        """The gate's bucket for ``key`` heard on this vehicle's side: per pair, since every vehicle
        asks the same ``v2x/rsu/{id}/time`` and one vehicle's rate must not starve the others."""
        return f"{self.side.vehicle_id or ''}|{key}"

    def direction(self, name: str) -> DirectionStats:
        return self.uplink if name == "uplink" else self.downlink

    def as_dict(self, rsu_xy_m: tuple[float, float] | None) -> dict[str, Any]:
        """This pair's stats: profile, counters per direction, pose and distance, open queries, in flight."""
        return {
            "vehicle_id": self.vehicle_id,
            "profile": self.model.profile.name,
            "uplink": self.uplink.as_dict(),
            "downlink": self.downlink.as_dict(),
            "pose": self.position.as_dict(rsu_xy_m),
            "open_queries": len(self.queries),
            "in_flight": {d: {"messages": f.messages, "bytes": f.bytes} for d, f in self.in_flight.items()},
        }


def control_targets(pairs: list[VehiclePair], control: LinkControl) -> list[VehiclePair]:
    """The pairs ``control`` acts on: every pair, or the one whose vehicle it names (may be none)."""
    if control.vehicle_id is None:
        return list(pairs)
    return [p for p in pairs if p.vehicle_id == control.vehicle_id]


def apply_to_pairs(pairs: list[VehiclePair], control: LinkControl, now_ns: int) -> str:
    """Apply ``control`` to each of ``pairs`` as of ``now_ns``; its description (``apply_control``).

    ValueError (nothing changed) for an unknown profile, or when ``pairs`` is empty.
    """
    if not pairs:
        raise ValueError(f"no vehicle {control.vehicle_id!r} on this emulator")
    results = [apply_control(p.model, control, now_ns) for p in pairs]
    where = f" (vehicle {control.vehicle_id})" if control.vehicle_id is not None else ""
    return results[0] + where


def merged_direction(stats: list[DirectionStats]) -> dict[str, Any]:
    """One direction's counters summed over pairs; delays merged (count, mean, min, max in ms)."""
    total = DirectionStats()
    delay = RunningStats()
    for s in stats:
        total.received += s.received
        total.delivered += s.delivered
        total.dropped += s.dropped
        delay.count += s.delay_ms.count
        delay.total += s.delay_ms.total
        delay.minimum = min(delay.minimum, s.delay_ms.minimum)
        delay.maximum = max(delay.maximum, s.delay_ms.maximum)
    total.delay_ms = delay
    return total.as_dict()


def merged_pose(pairs: list[VehiclePair], rsu_xy_m: tuple[float, float] | None) -> dict[str, Any]:
    """Pose counters over pairs: the one pair's own dict, else sums (no single id or distance)."""
    if len(pairs) == 1:
        return pairs[0].position.as_dict(rsu_xy_m)
    refused: Counter[str] = Counter()
    for p in pairs:
        refused.update(p.position.refused)
    return {"vehicle_id": None, "received": sum(p.position.received for p in pairs),
            "rejected": sum(p.position.rejected for p in pairs), "refused": dict(refused), "distance_m": None}


def pairs_summary(pairs: list[VehiclePair], rsu_xy_m: tuple[float, float] | None) -> dict[str, Any]:
    """The stats fields over all pairs (sums), plus ``pairs``: each pair's own, in configured order.

    ``profile``: the profile all pairs share, or ``"mixed"`` after a control switched one.
    """
    names = {p.model.profile.name for p in pairs}
    return {
        "profile": names.pop() if len(names) == 1 else "mixed",
        "uplink": merged_direction([p.uplink for p in pairs]),
        "downlink": merged_direction([p.downlink for p in pairs]),
        "pose": merged_pose(pairs, rsu_xy_m),
        "open_queries": sum(len(p.queries) for p in pairs),
        "in_flight": {d: {"messages": sum(p.in_flight[d].messages for p in pairs),
                          "bytes": sum(p.in_flight[d].bytes for p in pairs)} for d in DIRECTIONS},
        "pairs": [p.as_dict(rsu_xy_m) for p in pairs],
    }
