"""Conversion between the wire's object columns and ``ObjectArray``, and fitting objects to the wire.

``schemas.columns.ObjectColumns`` holds a list's objects as an (N, K) matrix in the column order
``id, cls, x, y, z, length, width, height, yaw, vx, vy, ax, ay, yaw_rate, cov_xx, cov_xy, cov_yy,
cov_vxx, cov_vxy, cov_vyy, confidence, age_s[, sources]``; both conversions are column slices and
stacks, no per-object work.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from itertools import accumulate

import numpy as np

from schemas import messages as m
from schemas.columns import COLUMN, ObjectColumns
from schemas.messages import SOURCE_RSU, SOURCE_VEHICLE, ObjectState

from v2i.core.frames import wrap_angle
from v2i.core.jit import F64, I64, IN_F1, IN_I1, OUT_F2, OUT_I1, kernel
from v2i.core.objects import ObjectArray

_C = COLUMN
_COV = np.array([_C["cov_xx"], _C["cov_xy"], _C["cov_xy"], _C["cov_yy"]])  # row-major [[xx, xy], [xy, yy]]
_VCOV = np.array([_C["cov_vxx"], _C["cov_vxy"], _C["cov_vxy"], _C["cov_vyy"]])


def objects_from_states(states: ObjectColumns | Sequence[ObjectState]) -> ObjectArray:
    """ObjectArray of a list's objects (in the frame the message states); ``sources`` 0 unless fused.

    ``states``: the message's ObjectColumns (or, for small hand-made lists, object models).
    """
    cols = states if isinstance(states, ObjectColumns) else ObjectColumns.from_states(states)
    n, v, codes = len(cols), cols.values, cols.codes
    if n == 0:
        return ObjectArray.empty()
    return ObjectArray(
        ids=codes[:, _C["id"]].copy(), cls=codes[:, _C["cls"]].copy(), xy=v[:, _C["x"]:_C["y"] + 1].copy(),
        z=v[:, _C["z"]].copy(), lwh=v[:, _C["length"]:_C["height"] + 1].copy(), yaw=v[:, _C["yaw"]].copy(),
        vxy=v[:, _C["vx"]:_C["vy"] + 1].copy(), axy=v[:, _C["ax"]:_C["ay"] + 1].copy(),
        yaw_rate=v[:, _C["yaw_rate"]].copy(), cov_xy=_gathered(v, _COV).reshape(n, 2, 2),
        cov_vxy=_gathered(v, _VCOV).reshape(n, 2, 2), confidence=v[:, _C["confidence"]].copy(),
        age_s=v[:, _C["age_s"]].copy(),
        sources=codes[:, _C["sources"]].copy() if cols.fused else np.zeros(n, np.int64),
    )


def _gathered(v: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """``v[:, columns]`` (N, K) of a C-ordered table, its very values and memory order (the column-major
    order numpy's advanced indexing gives here, kept for the products that read it), by one ``take``."""
    return v.T.take(columns, axis=0).T


def wire_sources(masks: np.ndarray) -> np.ndarray:
    """The wire's one-byte sources (K,) of K int64 source bitmasks of the OBU's tracker: bit 0
    (own vehicle) stays SOURCE_VEHICLE, any of bits 1..62 (RSU / peer slots) becomes SOURCE_RSU."""
    masks = np.asarray(masks, dtype=np.int64)
    return (masks & SOURCE_VEHICLE) | np.where((masks & ~SOURCE_VEHICLE) != 0, SOURCE_RSU, 0)


def states_from_objects(objs: ObjectArray, fused: bool = False) -> ObjectColumns:
    """The wire's object columns of an ObjectArray; ``fused`` adds the ``sources`` bitmask, folded
    into the wire's byte (``wire_sources``). Validated and quantised as arrays (an
    ``InvalidMessage`` names the first object and column out of range).

    Ids must be non-negative (track ids); confidence is clipped to [0, 1] and age to >= 0
    (``fit_to_wire`` clips the rest).
    """
    n = len(objs)
    table = np.empty((n, len(COLUMN) if fused else len(COLUMN) - 1))
    table[:, _C["id"]], table[:, _C["cls"]] = objs.ids, objs.cls
    table[:, _C["x"]:_C["y"] + 1], table[:, _C["z"]] = objs.xy, objs.z
    table[:, _C["length"]:_C["height"] + 1], table[:, _C["yaw"]] = objs.lwh, objs.yaw
    table[:, _C["vx"]:_C["vy"] + 1], table[:, _C["ax"]:_C["ay"] + 1] = objs.vxy, objs.axy
    table[:, _C["yaw_rate"]] = objs.yaw_rate
    _put_cov(table, _C["cov_xx"], objs.cov_xy)
    _put_cov(table, _C["cov_vxx"], objs.cov_vxy)
    table[:, _C["confidence"]] = np.clip(objs.confidence, 0.0, 1.0)
    table[:, _C["age_s"]] = np.maximum(objs.age_s, 0.0)
    if fused:
        table[:, _C["sources"]] = wire_sources(objs.sources)
    return ObjectColumns.from_values(table, fused)


def fit_to_wire(objs: ObjectArray, max_objects: int = m.MAX_OBJECTS) -> tuple[ObjectArray, Counter[str]]:
    """The objects as the wire can carry them, never raising, and what it took (counts by reason).

    A row with a non-finite value is dropped (``not_finite``), one whose position lies outside
    the wire's range too (``out_of_range``: no clipped position is a true one); the rest are
    clipped to the wire's ranges (``clipped``: speeds, accelerations, yaw rates, variances,
    sizes, heights, confidence, age; yaw wrapped; ids modulo 2^32); beyond ``max_objects`` the
    objects farthest from the frame's origin (in base_link: the ego) are dropped (``truncated``).
    Every check and clip runs once on the (N, 22) table of the real-valued columns (``_LAYOUT``).
    """
    table = _table(objs)
    fitted = _fit_in_place(table, objs, max_objects, _LO, _HI, _YAW)
    if fitted is not None:  # (cls and sources copied, as take copies them)
        ids, changed = fitted
        objs = objs.with_(cls=objs.cls.copy(), sources=objs.sources.copy())
        return _with_table(objs, ids, table), +Counter(clipped=changed)
    keep, counts = _kept_rows(table, objs.xy, max_objects)
    objs, table = objs.take(keep), table[keep]
    clipped = np.clip(table, _LO, _HI)
    clipped[:, _YAW] = wrap_angle(table[:, _YAW])
    ids = np.mod(objs.ids, 2**32)
    counts["clipped"] = int(((objs.ids != ids) | (table != clipped).any(axis=1)).sum())
    return _with_table(objs, ids, clipped), +counts


def wire_columns(objs: ObjectArray, max_objects: int = m.MAX_OBJECTS, fused: bool = False
                 ) -> tuple[ObjectColumns, Counter[str]]:
    """``states_from_objects(fit_to_wire(objs, max_objects)[0], fused)`` and fit_to_wire's counts,
    from one table: the (N, 24) table of the wire's columns id .. age_s and each covariance's
    lower off-diagonal (which fit_to_wire checks and clips as well; the slot ``sources`` takes
    once they are counted) is checked and clipped in place of the (N, 22) ``_LAYOUT`` table and
    handed to ``ObjectColumns.from_values`` (no fitted ObjectArray, no second table). The same
    values in the same columns: the same codes."""
    n = len(objs)
    table = np.empty((n, _W_WIDTH))
    real = table[:, _W_REAL]  # (N, 22) view: x .. age_s, cov_xy[1, 0], cov_vxy[1, 0]
    for name, start, width in _W_SPANS:
        real[:, start:start + width] = getattr(objs, name).reshape(n, width)
    _put_cov(real, _W_COV[0], objs.cov_xy, _W_YX)
    _put_cov(real, _W_VCOV[0], objs.cov_vxy, _W_YX + 1)
    fitted = _fit_in_place(real, objs, max_objects, _W_LO, _W_HI, _W_YAW)
    if fitted is not None:
        ids, changed = fitted
        table[:, _C["id"]], table[:, _C["cls"]] = ids, objs.cls
        if fused:
            table[:, _C["sources"]] = wire_sources(objs.sources)  # over cov_xy[1, 0], counted
        return ObjectColumns.from_values(table[:, :len(COLUMN) if fused else len(COLUMN) - 1], fused), \
            +Counter(clipped=changed)
    keep, counts = _kept_rows(real, objs.xy, max_objects)
    rows = keep if len(keep) < n else slice(None)  # every row kept (the usual case): views, no copies
    table, old_ids = table[rows], objs.ids[rows]
    ids, real = np.mod(old_ids, 2**32), table[:, _W_REAL]
    clipped = np.clip(real, _W_LO, _W_HI)
    clipped[:, _W_YAW] = wrap_angle(real[:, _W_YAW])
    counts["clipped"] = int(((old_ids != ids) | (real != clipped).any(axis=1)).sum())
    table[:, _W_REAL] = clipped
    table[:, _C["id"]], table[:, _C["cls"]] = ids, objs.cls[rows]
    if fused:
        table[:, _C["sources"]] = wire_sources(objs.sources[rows])  # over cov_xy[1, 0], counted above
    return ObjectColumns.from_values(table[:, :len(COLUMN) if fused else len(COLUMN) - 1], fused), +counts


def _fit_in_place(real: np.ndarray, objs: ObjectArray, max_objects: int, lo: np.ndarray, hi: np.ndarray,
                  yaw: int) -> tuple[np.ndarray, int] | None:
    """The usual case of fit_to_wire and wire_columns (every row kept) in one compiled pass over ``real``
    (N, M), in place: (wire ids (N,), rows changed), or None (``real`` untouched) for the general path."""
    if len(objs) > max_objects or objs.ids.dtype != np.int64:
        return None
    ids = np.empty(len(objs), np.int64)
    changed = _fit_rows(real, objs.ids, ids, lo, hi, yaw, m.POSITION_MAX_M)
    return None if changed < 0 else (ids, changed)


@kernel(OUT_F2, IN_I1, OUT_I1, IN_F1, IN_F1, I64, F64)
def _fit_rows(real: np.ndarray, ids: np.ndarray, wire_ids: np.ndarray, lo: np.ndarray, hi: np.ndarray, yaw: int,
              position_max_m: float) -> int:
    """wire_columns' usual case, in place: -1 (``real`` untouched) unless every value of ``real`` (N, M)
    is finite and every position (columns 0, 1) within +-position_max_m; then each value clipped to
    [lo, hi] (M,) as np.clip does (x > lo ? x : lo, then v < hi ? v : hi), column ``yaw`` wrapped as
    ``wrap_angle`` ((x + pi) mod 2 pi - pi, the remainder taking the divisor's sign, as numpy's),
    wire_ids (N,) = ids mod 2^32; returns how many rows changed (``clipped``). -1 too unless ids, wire_ids
    have N rows and lo, hi M entries."""
    n, width = real.shape
    if len(ids) != n or len(wire_ids) != n or len(lo) != width or len(hi) != width or width < 2:
        return -1  # (read below without bounds checks: the general path raises instead)
    for i in range(n):
        if abs(real[i, 0]) > position_max_m or abs(real[i, 1]) > position_max_m:
            return -1
        for j in range(width):
            if not np.isfinite(real[i, j]):
                return -1
    changed = 0
    for i in range(n):
        wire_ids[i] = ids[i] % 4294967296
        row = wire_ids[i] != ids[i]
        for j in range(width):
            x = real[i, j]
            if j == yaw:
                v = (x + np.pi) % (2.0 * np.pi) - np.pi
            else:
                v = x if x > lo[j] else lo[j]
                v = v if v < hi[j] else hi[j]
            row = row or v != x
            real[i, j] = v
        changed += row
    return changed


def _put_cov(table: np.ndarray, xx: int, cov: np.ndarray, yx: int | None = None) -> None:
    """Covariances cov (N, 2, 2) into columns of ``table`` (N, M): xx, xy, yy at xx, xx + 1, xx + 2, and
    the lower off-diagonal at ``yx`` if given (slice copies, no gather)."""
    table[:, xx:xx + 2] = cov[:, 0, :]
    table[:, xx + 2] = cov[:, 1, 1]
    if yx is not None:
        table[:, yx] = cov[:, 1, 0]


def _kept_rows(real: np.ndarray, xy: np.ndarray, max_objects: int) -> tuple[np.ndarray, Counter[str]]:
    """(indices of the rows kept, counts): rows of ``real`` (N, M) with a non-finite value dropped,
    then those whose position ``xy`` (N, 2) is out of range, then the farthest beyond max_objects."""
    finite = np.isfinite(real)
    if finite.all() and (np.abs(xy) <= m.POSITION_MAX_M).all():  # the usual case: every row kept, in one pass
        counts, keep = Counter(), np.arange(len(real))
    else:
        finite = finite.all(axis=1)
        inside = finite & (np.abs(np.where(finite[:, None], xy, 0.0)) <= m.POSITION_MAX_M).all(axis=1)
        counts = Counter(not_finite=int((~finite).sum()), out_of_range=int((finite & ~inside).sum()))
        keep = np.flatnonzero(inside)
    if len(keep) > max_objects:
        counts["truncated"] = len(keep) - max_objects
        nearest = np.argsort(np.hypot(xy[keep, 0], xy[keep, 1]), kind="stable")[:max_objects]
        keep = keep[np.sort(nearest)]
    return keep, counts


# the real-valued columns of an ObjectArray as one (N, 22) table: (column, width, low, high) with
# the wire's ranges (``schemas.messages``); positions are not clipped (out of range is dropped),
# yaw is wrapped instead, a covariance's diagonal (xx, yy of its row-major 2x2) is >= 0
_LAYOUT = (
    ("xy", 2, -np.inf, np.inf), ("z", 1, -m.HEIGHT_MAX_M, m.HEIGHT_MAX_M), ("lwh", 3, 0.0, m.SIZE_MAX_M),
    ("yaw", 1, -np.inf, np.inf), ("vxy", 2, -m.SPEED_MAX_MPS, m.SPEED_MAX_MPS),
    ("axy", 2, -m.ACCEL_MAX_MPS2, m.ACCEL_MAX_MPS2), ("yaw_rate", 1, -m.YAW_RATE_MAX, m.YAW_RATE_MAX),
    ("cov_xy", 4, -m.VARIANCE_MAX, m.VARIANCE_MAX), ("cov_vxy", 4, -m.VARIANCE_MAX, m.VARIANCE_MAX),
    ("confidence", 1, 0.0, 1.0), ("age_s", 1, 0.0, m.AGE_MAX_S),
)
_LO = np.concatenate([np.full(w, lo) for _, w, lo, _ in _LAYOUT])
_HI = np.concatenate([np.full(w, hi) for _, w, _, hi in _LAYOUT])
_ENDS = list(accumulate(width for _, width, _, _ in _LAYOUT))
_SPAN = {name: slice(end - width, end) for (name, width, _, _), end in zip(_LAYOUT, _ENDS)}  # column -> slice
_LO[[_SPAN["cov_xy"].start, _SPAN["cov_xy"].start + 3, _SPAN["cov_vxy"].start, _SPAN["cov_vxy"].start + 3]] = 0.0
_YAW = _SPAN["yaw"].start

# wire_columns' table: the wire's columns id .. age_s (COLUMN order), then cov_xy[1, 0] (where a
# fused list's sources go once it is counted) and cov_vxy[1, 0]; _W_REAL: its real-valued columns,
# in _LAYOUT's bounds (_W_FROM: their _LAYOUT columns); _W_SPANS: (ObjectArray column, start, width)
_W_WIDTH = _C["age_s"] + 3
_W_REAL = slice(_C["x"], _W_WIDTH)
_W_SPANS = tuple((name, _C[first] - _C["x"], width) for name, first, width in (
    ("xy", "x", 2), ("z", "z", 1), ("lwh", "length", 3), ("yaw", "yaw", 1), ("vxy", "vx", 2), ("axy", "ax", 2),
    ("yaw_rate", "yaw_rate", 1), ("confidence", "confidence", 1), ("age_s", "age_s", 1)))
_W_YX = _C["age_s"] + 1 - _C["x"]  # cov_xy[1, 0] in _W_REAL, cov_vxy[1, 0] after it
_W_COV = [_C["cov_xx"] - _C["x"], _C["cov_xy"] - _C["x"], _C["cov_yy"] - _C["x"], _W_YX]  # row-major 0, 1, 3, 2
_W_VCOV = [_C["cov_vxx"] - _C["x"], _C["cov_vxy"] - _C["x"], _C["cov_vyy"] - _C["x"], _W_YX + 1]
_W_YAW = _C["yaw"] - _C["x"]
_W_FROM = np.empty(_W_YX + 2, np.int64)
for _name, _start, _width in _W_SPANS:
    _W_FROM[_start:_start + _width] = range(_SPAN[_name].start, _SPAN[_name].stop)
_W_FROM[_W_COV] = _SPAN["cov_xy"].start + np.array([0, 1, 3, 2])
_W_FROM[_W_VCOV] = _SPAN["cov_vxy"].start + np.array([0, 1, 3, 2])
_W_LO, _W_HI = _LO[_W_FROM], _HI[_W_FROM]
del _name, _start, _width


def _table(objs: ObjectArray) -> np.ndarray:
    """(N, 22) float64: the real-valued columns side by side in ``_LAYOUT`` order."""
    n = len(objs)
    return np.concatenate([getattr(objs, name).reshape(n, width) for name, width, _, _ in _LAYOUT], axis=1,
                          dtype=np.float64)


def _with_table(objs: ObjectArray, ids: np.ndarray, table: np.ndarray) -> ObjectArray:
    """``objs`` with these ids and its real-valued columns read back from ``table`` (N, 22)."""
    columns = {name: table[:, _SPAN[name]].reshape(getattr(objs, name).shape) for name, _, _, _ in _LAYOUT}
    return objs.with_(ids=ids, **columns)
