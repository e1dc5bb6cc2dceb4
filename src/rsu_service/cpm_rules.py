"""CPM generation rules (pure): which of the RSU's tracks go into the next collective
perception message, and whether a message goes at all (RSU ``--cpm-rules``).

ETSI TS 103 324 V2.1.1 (2023-06), clause 6.1.2, with the values of Annex F, Table F.1. The
clause text itself was not at hand; the rules and values below are as two open
implementations of V2.1.1 quote and implement them, and they agree: Artery's ``CpService``
(``checkPerceivedObjectInclusion``, parameters ``minPositionChangeThreshold``,
``minGroundSpeedChangeThreshold``, ``minGroundVelocityOrientationChangeThreshold``,
``T_GenCpmMin``, ``T_GenCpmMax``) and a Rust CP basic service whose documentation cites
§6.1.2.1, §6.1.2.3 rules 1 a-b and 2 a-e and Table F.1 (both read on the public code store).

=============================  ==========  ======================================================
rule                           value       source
=============================  ==========  ======================================================
T_GenCpmMin: generation        100 ms      §6.1.2.1; Table F.1. A generation event sooner than
events no closer than                      this after the last CPM sends nothing.
T_GenCpmMax: a CPM at least    1000 ms     §6.1.2.1; Table F.1. With no object to include, a CPM
this often                                 (empty) still goes once this long has passed: the
                                           standard's periodic content, the sensor information
                                           container (every T_AddSensorInformation, 1 s, §6.1.2.2),
                                           is not sent by v2i; the empty CPM keeps the RSU heard.
Type-B (vehicles,              4 m         §6.1.2.3 rule 2: included when first detected since
motorcyclists)                 0.5 m/s     the last generation event (a), or, since it was last
                               4 degrees   included, its position moved more than 4 m (b), its
                               1000 ms     ground speed changed more than 0.5 m/s (c), the
                                           orientation of its ground velocity changed more than
                                           4 degrees (d), or T_GenCpmMax or more has passed (e).
Type-A (pedestrians,           500 ms      §6.1.2.3 rule 1: included when first detected since
cyclists)                                  the last generation event (a); when any Type-A object
                                           has gone T_GenCpmMax / 2 or more without inclusion,
                                           every Type-A object is included (b).
=============================  ==========  ======================================================

"More than" is strict for rules 2 b-d, as the issue and Artery have it (one secondary
source reads "at least" for the orientation: the difference is one 0.1-degree code). The
orientation compared is that of the ground velocity, ``atan2(vy, vx)``; below
``standing_speed_mps`` a velocity has no direction and the track's yaw stands in.

v2i classes: PEDESTRIAN and CYCLIST are Type-A (ETSI VRU profiles pedestrian and
bicyclistAndLightVruVehicle); every other class is Type-B, MOTORCYCLE included (profile
motorcyclist) and UNKNOWN (sent as a vehicle sub-class). Not modelled: the object
perception quality threshold (the RSU publishes confirmed tracks only, which stands in for
it), the optional look-ahead that pulls objects due at the next event into this one (a
"may"), perception regions and the sensor information container.

State: per object id, what was last sent (time, position, speed, orientation); an id absent
from a generation event is forgotten, so a re-acquired track is "first detected" again.
``select`` decides without changing the state; ``commit`` records what was actually sent
(segmentation may leave objects out: ``rsu_service.cpm_segments``). Times are ns of a clock
that does not step (the RSU's monotonic clock).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from schemas.classes import ObjectClass

TYPE_A_CLASSES = (int(ObjectClass.PEDESTRIAN), int(ObjectClass.CYCLIST))  # ETSI VRU pedestrian / bicyclist


@dataclass(frozen=True)
class CpmRulesConfig:
    """TS 103 324 V2.1.1 §6.1.2 thresholds (Table F.1 values)."""

    min_position_change_m: float = 4.0  # minPositionChangeThreshold
    min_speed_change_mps: float = 0.5  # minGroundSpeedChangeThreshold
    min_orientation_change_deg: float = 4.0  # minGroundVelocityOrientationChangeThreshold
    t_gen_cpm_min_ns: int = 100_000_000  # T_GenCpmMin
    t_gen_cpm_max_ns: int = 1_000_000_000  # T_GenCpmMax (Type-B refresh, and a CPM at least this often)
    standing_speed_mps: float = 0.1  # below: the velocity has no direction, the yaw stands in (v2i's choice)

    @property
    def type_a_refresh_ns(self) -> int:
        """T_GenCpmMax / 2: a Type-A object this long without inclusion brings every Type-A object."""
        return self.t_gen_cpm_max_ns // 2


@dataclass(frozen=True)
class Selection:
    """One generation event's decision: ``send`` a CPM (possibly empty) carrying the objects at
    ``indices`` (ascending rows of the event's arrays)."""

    send: bool
    indices: np.ndarray  # (M,) int64


@dataclass
class _Sent:
    """Per-object state at its last inclusion: time (ns), position (m), speed (m/s), orientation (rad)."""

    t_ns: np.ndarray
    xy: np.ndarray
    speed: np.ndarray
    course: np.ndarray


def type_a(cls: np.ndarray) -> np.ndarray:
    """(N,) bool: the v2i classes ``cls`` that are Type-A (pedestrian, cyclist)."""
    return np.isin(np.asarray(cls).astype(np.int64), TYPE_A_CLASSES)


def ground_course(vxy: np.ndarray, yaw: np.ndarray, standing_speed_mps: float) -> np.ndarray:
    """(N,) orientation (rad) of the ground velocity, atan2(vy, vx); the yaw where |v| <= standing speed."""
    moving = np.hypot(vxy[:, 0], vxy[:, 1]) > standing_speed_mps
    return np.where(moving, np.arctan2(vxy[:, 1], vxy[:, 0]), yaw)


class CpmInclusion:
    """Which tracks go into each CPM (TS 103 324 §6.1.2.3) and whether a CPM goes (§6.1.2.1)."""

    def __init__(self, config: CpmRulesConfig = CpmRulesConfig()):
        self.config = config
        self._ids = np.zeros(0, np.int64)  # sorted ids of the last event's tracks that were ever sent
        self._sent = _Sent(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0), np.zeros(0))
        self._last_cpm_ns: int | None = None
        self._pending: tuple[int, np.ndarray] | None = None  # select's (t_ns, rule per row) for commit
        self.included_by: Counter[str] = Counter()  # objects sent, by the rule that included them
        self.events: Counter[str] = Counter()  # generation events: sent, too_soon, nothing_to_send

    def select(self, t_ns: int, ids: np.ndarray, xy: np.ndarray, vxy: np.ndarray, yaw: np.ndarray,
               cls: np.ndarray) -> Selection:
        """The decision for a generation event at ``t_ns`` over N tracks: ``ids`` (N,), ``xy`` (N, 2) m,
        ``vxy`` (N, 2) m/s, ``yaw`` (N,) rad, ``cls`` (N,) v2i classes. No state changes (``commit``)."""
        cfg = self.config
        ids = np.asarray(ids).astype(np.int64)
        if self._too_soon(t_ns):
            return Selection(False, np.zeros(0, np.int64))  # T_GenCpmMin: too soon after the last CPM
        xy, vxy = np.asarray(xy, np.float64).reshape(-1, 2), np.asarray(vxy, np.float64).reshape(-1, 2)
        speed = np.hypot(vxy[:, 0], vxy[:, 1])
        course = ground_course(vxy, np.asarray(yaw, np.float64), cfg.standing_speed_mps)
        vru = type_a(cls)
        row = np.searchsorted(self._ids, ids)
        known = np.zeros(len(ids), bool)
        if len(self._ids):
            known = (row < len(self._ids)) & (self._ids[np.minimum(row, len(self._ids) - 1)] == ids)
        rule = np.full(len(ids), "", dtype=object)
        rule[~known] = "new"  # rules 1 a, 2 a: first detected since the last generation event
        k = np.flatnonzero(known)
        age_ns = t_ns - self._sent.t_ns[row[k]]
        b = ~vru[k]
        for name, fired in self._type_b_rules(row[k], xy[k], speed[k], course[k], age_ns):
            rule[k[b & fired]] = name  # the last assignment wins: position, speed, heading, refresh
        # rule 1 b: a known Type-A object T_GenCpmMax / 2 or more without inclusion brings every Type-A object
        if (vru[k] & (age_ns >= cfg.type_a_refresh_ns)).any():
            rule[k[vru[k]]] = "vru_refresh"
        indices = np.flatnonzero(rule != "").astype(np.int64)
        self._pending = (t_ns, rule)
        due = self._last_cpm_ns is None or t_ns - self._last_cpm_ns >= cfg.t_gen_cpm_max_ns
        return Selection(bool(len(indices)) or due, indices)

    def commit(self, t_ns: int, ids: np.ndarray, xy: np.ndarray, vxy: np.ndarray, yaw: np.ndarray,
               sent: np.ndarray | None) -> None:
        """Record the generation event at ``t_ns`` over the same N tracks as ``select``: the rows
        ``sent`` went out (None: no CPM went). Ids absent from ``ids`` are forgotten."""
        cfg = self.config
        ids = np.asarray(ids).astype(np.int64)
        pending, self._pending = self._pending, None
        keep = np.isin(self._ids, ids)  # a track no longer listed is forgotten (new if it comes back)
        self._ids, self._sent = self._ids[keep], _Sent(*(a[keep] for a in vars(self._sent).values()))
        if sent is None:
            self.events["too_soon" if self._too_soon(t_ns) else "nothing_to_send"] += 1
            return
        self.events["sent"] += 1
        self._last_cpm_ns = t_ns
        sent = np.asarray(sent, np.int64)
        if pending is not None and pending[0] == t_ns and len(pending[1]) == len(ids):
            self.included_by.update(pending[1][sent].tolist())
        xy, vxy = np.asarray(xy, np.float64).reshape(-1, 2), np.asarray(vxy, np.float64).reshape(-1, 2)
        new = _Sent(np.full(len(sent), t_ns, np.int64), xy[sent], np.hypot(vxy[sent, 0], vxy[sent, 1]),
                    ground_course(vxy[sent], np.asarray(yaw, np.float64)[sent], cfg.standing_speed_mps))
        old = ~np.isin(self._ids, ids[sent])  # the sent rows replace their ids' states; the others keep theirs
        all_ids = np.concatenate([self._ids[old], ids[sent]])
        order = np.argsort(all_ids, kind="stable")
        self._ids = all_ids[order]
        self._sent = _Sent(*(np.concatenate([a[old], c])[order]
                             for a, c in zip(vars(self._sent).values(), vars(new).values())))

    def _type_b_rules(self, r: np.ndarray, xy: np.ndarray, speed: np.ndarray, course: np.ndarray,
                      age_ns: np.ndarray) -> tuple[tuple[str, np.ndarray], ...]:
        """Rules 2 e, d, c, b as (name, fired (K,)) for K known objects whose last-sent states are rows ``r``."""
        cfg, last = self.config, self._sent
        # 2 b: |p - p_last| > 4 m; 2 c: ||v| - |v_last|| > 0.5 m/s
        moved = np.hypot(*(xy - last.xy[r]).T) > cfg.min_position_change_m
        sped = np.abs(speed - last.speed[r]) > cfg.min_speed_change_mps
        # 2 d: |wrap(course - course_last)| > 4 degrees, wrap to (-pi, pi] by the angle of exp(i d)
        turned = np.abs(np.angle(np.exp(1j * (course - last.course[r])))) > np.deg2rad(cfg.min_orientation_change_deg)
        # 2 e: t - t_last >= T_GenCpmMax
        return ("refresh", age_ns >= cfg.t_gen_cpm_max_ns), ("heading", turned), ("speed", sped), ("position", moved)

    def _too_soon(self, t_ns: int) -> bool:
        """Whether ``t_ns`` is less than T_GenCpmMin after the last CPM."""
        return self._last_cpm_ns is not None and t_ns - self._last_cpm_ns < self.config.t_gen_cpm_min_ns
