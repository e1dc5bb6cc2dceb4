"""Conversion between wire object models and ``ObjectArray``, and fitting objects to the wire."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

import numpy as np

from schemas import messages as m
from schemas.messages import SOURCE_RSU, SOURCE_VEHICLE, FusedObject, ObjectState

from .frames import wrap_angle
from .objects import ObjectArray

_SCALARS = ("id", "cls", "x", "y", "z", "length", "width", "height", "yaw", "vx", "vy", "ax", "ay",
            "yaw_rate", "cov_xx", "cov_xy", "cov_yy", "cov_vxx", "cov_vxy", "cov_vyy", "confidence", "age_s")


def _sym2(xx: np.ndarray, xy: np.ndarray, yy: np.ndarray) -> np.ndarray:
    """(N, 2, 2) symmetric matrices [[xx, xy], [xy, yy]]."""
    return np.stack([np.stack([xx, xy], -1), np.stack([xy, yy], -1)], -2)


def objects_from_states(states: Sequence[ObjectState]) -> ObjectArray:
    """ObjectArray of wire objects (in the frame the message states)."""
    if not states:
        return ObjectArray.empty()
    col = {name: np.array([getattr(s, name) for s in states]) for name in _SCALARS}
    sources = np.array([getattr(s, "sources", 0) for s in states], dtype=np.int64)
    return ObjectArray(
        ids=col["id"].astype(np.int64), cls=col["cls"].astype(np.int64),
        xy=np.column_stack([col["x"], col["y"]]), z=col["z"],
        lwh=np.column_stack([col["length"], col["width"], col["height"]]), yaw=col["yaw"],
        vxy=np.column_stack([col["vx"], col["vy"]]), axy=np.column_stack([col["ax"], col["ay"]]),
        yaw_rate=col["yaw_rate"], cov_xy=_sym2(col["cov_xx"], col["cov_xy"], col["cov_yy"]),
        cov_vxy=_sym2(col["cov_vxx"], col["cov_vxy"], col["cov_vyy"]), confidence=col["confidence"],
        age_s=col["age_s"], sources=sources,
    )


def wire_sources(masks: np.ndarray) -> np.ndarray:
    """The wire's one-byte sources (K,) of K int64 source bitmasks of the OBU's tracker: bit 0
    (own vehicle) stays SOURCE_VEHICLE, any of bits 1..62 (RSU / peer slots) becomes SOURCE_RSU."""
    masks = np.asarray(masks, dtype=np.int64)
    return (masks & SOURCE_VEHICLE) | np.where((masks & ~SOURCE_VEHICLE) != 0, SOURCE_RSU, 0)


def states_from_objects(objs: ObjectArray, fused: bool = False) -> tuple[ObjectState, ...]:
    """Wire objects of an ObjectArray; ``fused`` adds the ``sources`` bitmask, folded into the
    wire's byte (``wire_sources``).

    Ids must be non-negative (track ids); values are clipped to the wire's ranges where
    physics allows none outside them (sizes >= 0, confidence in [0, 1]).
    """
    model = FusedObject if fused else ObjectState
    sources = wire_sources(objs.sources) if fused else None
    out = []
    for i in range(len(objs)):
        kw = dict(
            id=int(objs.ids[i]), cls=int(objs.cls[i]), x=float(objs.xy[i, 0]), y=float(objs.xy[i, 1]),
            z=float(objs.z[i]), length=float(objs.lwh[i, 0]), width=float(objs.lwh[i, 1]),
            height=float(objs.lwh[i, 2]), yaw=float(objs.yaw[i]), vx=float(objs.vxy[i, 0]),
            vy=float(objs.vxy[i, 1]), ax=float(objs.axy[i, 0]), ay=float(objs.axy[i, 1]),
            yaw_rate=float(objs.yaw_rate[i]), cov_xx=float(objs.cov_xy[i, 0, 0]),
            cov_xy=float(objs.cov_xy[i, 0, 1]), cov_yy=float(objs.cov_xy[i, 1, 1]),
            cov_vxx=float(objs.cov_vxy[i, 0, 0]), cov_vxy=float(objs.cov_vxy[i, 0, 1]),
            cov_vyy=float(objs.cov_vxy[i, 1, 1]),
            confidence=float(np.clip(objs.confidence[i], 0.0, 1.0)), age_s=float(max(objs.age_s[i], 0.0)),
        )
        if fused:
            kw["sources"] = int(sources[i])
        out.append(model(**kw))
    return tuple(out)


def fit_to_wire(objs: ObjectArray, max_objects: int = m.MAX_OBJECTS) -> tuple[ObjectArray, Counter[str]]:
    """The objects as the wire can carry them, never raising, and what it took (counts by reason).

    A row with a non-finite value is dropped (``not_finite``), one whose position lies outside
    the wire's range too (``out_of_range``: no clipped position is a true one); the rest are
    clipped to the wire's ranges (``clipped``: speeds, accelerations, yaw rates, variances,
    sizes, heights, confidence, age; yaw wrapped; ids modulo 2^32); beyond ``max_objects`` the
    objects farthest from the frame's origin (in base_link: the ego) are dropped (``truncated``).
    """
    n = len(objs)
    finite = np.ones(n, bool)
    for column in _values(objs):
        finite &= np.isfinite(_rows(column)).all(axis=1)
    inside = finite & (np.abs(np.where(finite[:, None], objs.xy, 0.0)) <= m.POSITION_MAX_M).all(axis=1)
    counts = Counter(not_finite=int((~finite).sum()), out_of_range=int((finite & ~inside).sum()))
    objs = objs.take(inside)
    if len(objs) > max_objects:
        counts["truncated"] = len(objs) - max_objects
        nearest = np.argsort(np.hypot(objs.xy[:, 0], objs.xy[:, 1]), kind="stable")[:max_objects]
        objs = objs.take(np.sort(nearest))
    clipped = _clipped(objs)
    changed = objs.ids != clipped.ids
    for before, after in zip(_values(objs), _values(clipped)):
        changed |= _rows(before != after).any(axis=1)
    counts["clipped"] = int(changed.sum())
    return clipped, +counts


def _rows(a: np.ndarray) -> np.ndarray:
    """(N, k): each row's values flattened (also for N = 0)."""
    return a.reshape(len(a), int(np.prod(a.shape[1:], dtype=int)))


def _values(objs: ObjectArray) -> list[np.ndarray]:
    """The real-valued columns of the objects."""
    return [objs.xy, objs.z, objs.lwh, objs.yaw, objs.vxy, objs.axy, objs.yaw_rate, objs.cov_xy, objs.cov_vxy,
            objs.confidence, objs.age_s]


def _clipped(objs: ObjectArray) -> ObjectArray:
    """Every value clipped into its wire range (ranges from ``schemas.messages``), yaw wrapped."""

    def cov(c: np.ndarray) -> np.ndarray:
        out = np.clip(c, -m.VARIANCE_MAX, m.VARIANCE_MAX)
        out[:, [0, 1], [0, 1]] = np.clip(c[:, [0, 1], [0, 1]], 0.0, m.VARIANCE_MAX)
        return out

    return objs.with_(
        ids=np.mod(objs.ids, 2**32), z=np.clip(objs.z, -m.HEIGHT_MAX_M, m.HEIGHT_MAX_M),
        lwh=np.clip(objs.lwh, 0.0, m.SIZE_MAX_M), yaw=wrap_angle(objs.yaw),
        vxy=np.clip(objs.vxy, -m.SPEED_MAX_MPS, m.SPEED_MAX_MPS),
        axy=np.clip(objs.axy, -m.ACCEL_MAX_MPS2, m.ACCEL_MAX_MPS2),
        yaw_rate=np.clip(objs.yaw_rate, -m.YAW_RATE_MAX, m.YAW_RATE_MAX), cov_xy=cov(objs.cov_xy),
        cov_vxy=cov(objs.cov_vxy), confidence=np.clip(objs.confidence, 0.0, 1.0),
        age_s=np.clip(objs.age_s, 0.0, m.AGE_MAX_S),
    )
