"""Conversion between wire object models and ``ObjectArray``."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from schemas.messages import FusedObject, ObjectState

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


def states_from_objects(objs: ObjectArray, fused: bool = False) -> tuple[ObjectState, ...]:
    """Wire objects of an ObjectArray; ``fused`` adds the ``sources`` bitmask.

    Ids must be non-negative (track ids); values are clipped to the wire's ranges where
    physics allows none outside them (sizes >= 0, confidence in [0, 1]).
    """
    model = FusedObject if fused else ObjectState
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
            kw["sources"] = int(objs.sources[i])
        out.append(model(**kw))
    return tuple(out)
