"""Struct-of-arrays object set, the currency of every pure algorithm.

N objects; every array has first dimension N. Units: metres, radians, seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import numpy as np

from schemas.messages import UNKNOWN_VELOCITY_VAR  # per-axis velocity variance meaning "no velocity"


def _col(n: int, width: int | None = None, dtype=np.float64) -> np.ndarray:
    return np.zeros((n,) if width is None else (n, width), dtype=dtype)


@dataclass(frozen=True)
class ObjectArray:
    """N objects in one frame at one time.

    ids (N,) int64, cls (N,) int64 (``ObjectClass`` codes), xy (N, 2) m, z (N,) m,
    lwh (N, 3) m, yaw (N,) rad, vxy (N, 2) m/s, axy (N, 2) m/s^2, yaw_rate (N,) rad/s,
    cov_xy (N, 2, 2) m^2 position covariance, cov_vxy (N, 2, 2) m^2/s^2 velocity covariance
    (``UNKNOWN_VELOCITY_VAR`` on the diagonal: no velocity measured), confidence (N,) in
    [0, 1], age_s (N,) s, sources (N,) int64 bitmask (1 vehicle, 2 RSU).
    """

    ids: np.ndarray
    cls: np.ndarray
    xy: np.ndarray
    z: np.ndarray
    lwh: np.ndarray
    yaw: np.ndarray
    vxy: np.ndarray
    axy: np.ndarray = field(default=None)  # type: ignore[assignment]
    yaw_rate: np.ndarray = field(default=None)  # type: ignore[assignment]
    cov_xy: np.ndarray = field(default=None)  # type: ignore[assignment]
    confidence: np.ndarray = field(default=None)  # type: ignore[assignment]
    cov_vxy: np.ndarray = field(default=None)  # type: ignore[assignment]
    age_s: np.ndarray = field(default=None)  # type: ignore[assignment]
    sources: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        n = len(self.ids)
        defaults = {
            "axy": _col(n, 2),
            "yaw_rate": _col(n),
            "cov_xy": np.tile(np.eye(2), (n, 1, 1)),
            "confidence": np.ones(n),
            "cov_vxy": np.tile(np.eye(2) * UNKNOWN_VELOCITY_VAR, (n, 1, 1)),
            "age_s": _col(n),
            "sources": _col(n, dtype=np.int64),
        }
        for name, default in defaults.items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, default)
        for f in fields(self):
            arr = getattr(self, f.name)
            if len(arr) != n:
                raise ValueError(f"ObjectArray.{f.name} has {len(arr)} rows, ids has {n}")

    def __len__(self) -> int:
        return len(self.ids)

    def velocity_known(self) -> np.ndarray:
        """(N,) True where the velocity was measured or estimated: trace of cov_vxy below
        ``UNKNOWN_VELOCITY_VAR`` (an unknown velocity has that variance on each axis)."""
        return self.cov_vxy[:, 0, 0] + self.cov_vxy[:, 1, 1] < UNKNOWN_VELOCITY_VAR

    @classmethod
    def empty(cls) -> "ObjectArray":
        return cls(
            ids=_col(0, dtype=np.int64), cls=_col(0, dtype=np.int64), xy=_col(0, 2), z=_col(0),
            lwh=_col(0, 3), yaw=_col(0), vxy=_col(0, 2),
        )

    def take(self, index) -> "ObjectArray":
        """Rows selected by an index, index array or boolean mask (always an ObjectArray)."""
        if np.ndim(index) == 0:
            index = [index]
        return ObjectArray(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def with_(self, **changes) -> "ObjectArray":
        return replace(self, **changes)

    @staticmethod
    def concat(parts: "list[ObjectArray]") -> "ObjectArray":
        parts = [p for p in parts if len(p)]
        if not parts:
            return ObjectArray.empty()
        return ObjectArray(**{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(ObjectArray)})
