"""Struct-of-arrays object set, the currency of every pure algorithm.

N objects; every array has first dimension N. Units: metres, radians, seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import numpy as np

# m^2/s^2 (100 m/s std): the per-axis velocity variance meaning "no velocity measured"; the wire has the
# same meaning for it (schemas.limits re-exports it: the largest variance an object can carry)
UNKNOWN_VELOCITY_VAR = 1e4


def _col(n: int, width: int | None = None, dtype=np.float64) -> np.ndarray:
    return np.zeros((n,) if width is None else (n, width), dtype=dtype)


@dataclass(frozen=True, init=False)
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

    def __init__(self, ids: np.ndarray, cls: np.ndarray, xy: np.ndarray, z: np.ndarray, lwh: np.ndarray,
                 yaw: np.ndarray, vxy: np.ndarray, axy: np.ndarray = None, yaw_rate: np.ndarray = None,
                 cov_xy: np.ndarray = None, confidence: np.ndarray = None, cov_vxy: np.ndarray = None,
                 age_s: np.ndarray = None, sources: np.ndarray = None) -> None:
        """The dataclass's own __init__ (the fields in order, None: a default column), its frozen fields set
        into __dict__ at once instead of one object.__setattr__ each (~2.5 -> ~1 us for 14 columns)."""
        self.__dict__.update(ids=ids, cls=cls, xy=xy, z=z, lwh=lwh, yaw=yaw, vxy=vxy, axy=axy, yaw_rate=yaw_rate,
                             cov_xy=cov_xy, confidence=confidence, cov_vxy=cov_vxy, age_s=age_s, sources=sources)
        self.__post_init__()

    def __post_init__(self) -> None:
        columns = self.__dict__  # the frozen dataclass's fields, read and defaulted in place
        n = len(columns["ids"])
        for name, default in _DEFAULTS:  # built only for the columns left out
            if columns[name] is None:
                columns[name] = default(n)
        for name in _FIELDS:
            if len(columns[name]) != n:
                raise ValueError(f"ObjectArray.{name} has {len(columns[name])} rows, ids has {n}")

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
        """Rows selected by an index, index array or boolean mask (always an ObjectArray).

        A mask of the N rows or a 1-D integer index gathers every column with ``ndarray.take``
        (one mask scan, then ~0.3 us a column against ~0.6-0.8 us for indexing: the same rows);
        anything else is each column's ``column[index]``."""
        if np.ndim(index) == 0:
            index = [index]
        rows = np.asarray(index)
        if rows.dtype == bool and rows.shape == self.ids.shape:
            rows = rows.nonzero()[0]
        columns = self.__dict__
        out = object.__new__(ObjectArray)  # every column indexed alike: rows agree, no __post_init__ needed
        if rows.dtype.kind == "i" and rows.ndim == 1:
            out.__dict__.update({name: columns[name].take(rows, axis=0) for name in _FIELDS})
        else:
            out.__dict__.update({name: columns[name][index] for name in _FIELDS})
        return out

    def with_(self, **changes) -> "ObjectArray":
        """A copy with some columns replaced (``dataclasses.replace``). Fast path: when every new
        column (new ids included) is an array of the N rows the others have, only those are checked
        (the rest were at __init__: rows still agree)."""
        n = len(self.ids)
        for name, value in changes.items():
            if name not in _FIELD_SET or value is None or len(value) != n:
                return replace(self, **changes)  # a default, a bad column or other row counts: validate everything
        out = object.__new__(ObjectArray)
        out.__dict__.update(self.__dict__)
        out.__dict__.update(changes)
        return out

    @staticmethod
    def concat(parts: "list[ObjectArray]") -> "ObjectArray":
        parts = [p for p in parts if len(p)]
        if not parts:
            return ObjectArray.empty()
        return ObjectArray(**{name: np.concatenate([getattr(p, name) for p in parts]) for name in _FIELDS})


_TILES: dict[float, np.ndarray] = {}  # variance -> (K, 2, 2) var I_2, K grown as needed; 64 variances at most


def read_only(objs: ObjectArray) -> ObjectArray:
    """``objs`` with every column made read-only (in place): for objects several holders share."""
    for column in objs.__dict__.values():
        column.flags.writeable = False
    return objs


def diagonal_covariances(variance: float, n: int) -> np.ndarray:
    """(n, 2, 2) fresh copies of var I_2: ``np.tile(np.eye(2) * var, (n, 1, 1))`` (~4 us), copied from a slice
    of a kept tile (~0.5 us). Shared by the simulated sensors."""
    tile = _TILES.get(variance)
    if tile is None or len(tile) < n:
        if tile is None and len(_TILES) >= 64:
            _TILES.clear()
        rows = max(n, 64 if tile is None else 2 * len(tile))
        tile = _TILES[variance] = np.tile(np.eye(2) * variance, (rows, 1, 1))
    return tile[:n].copy()


_DEFAULTS = (  # (column, rows -> default) for the columns that may be left out
    ("axy", lambda n: _col(n, 2)),
    ("yaw_rate", _col),
    ("cov_xy", lambda n: diagonal_covariances(1.0, n)),
    ("confidence", np.ones),
    ("cov_vxy", lambda n: diagonal_covariances(UNKNOWN_VELOCITY_VAR, n)),
    ("age_s", _col),
    ("sources", lambda n: _col(n, dtype=np.int64)),
)
_FIELDS = tuple(f.name for f in fields(ObjectArray))
_FIELD_SET = frozenset(_FIELDS)
