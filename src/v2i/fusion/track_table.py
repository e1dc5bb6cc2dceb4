"""The tracker's table of tracks: columns of N tracks, and a store that keeps them in preallocated rows.

``TrackTable`` holds one array per column, first dimension N. Its ``seen_s`` column keeps the last
update time of each source bit *in use*: column j stands for source bit ``seen_bits[j]`` (an OBU
with 8 RSUs uses 9 of the 63 bits, so the table carries 9 columns, not 63); a table built
without ``seen_bits`` has one column per bit, 0 .. SOURCE_BITS - 1.

``TrackStore`` is the table a ``v2i.fusion.tracking.Tracker`` updates in place: the columns are
allocated for ``capacity`` rows (doubled when full, so N spawns cost O(N) copies in all, not one
copy of the whole table per spawn), the first ``n`` rows are the live tracks and ``view`` is the
TrackTable of those rows (views into the store: writing into it writes the store). Deleting
tracks moves the kept rows down in place; a source bit seen for the first time adds a column.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from operator import itemgetter

import numpy as np

from v2i.core.jit import B1, F64, I64, IN_B2, IN_F1, IN_F2, IN_F3, IN_I1, OUT_B1, OUT_F1, OUT_F2, OUT_I1, kernel

SOURCE_BITS = 63  # source bitmasks are int64: bit 0 own vehicle, bits 1..62 one per RSU / peer slot
_ALL_BITS = np.arange(SOURCE_BITS)
_MIN_CAPACITY = 64


@dataclass
class TrackTable:
    """Columns of N tracks: filter state x (N, n), P (N, n, n); ids, cls (N,); z (N,) m,
    lwh (N, 3) m, yaw (N,) rad, confidence (N,) of the last detection; hits (N,);
    born_s, updated_s (N,) s; seen_s (N, B) s, last update per source bit in use (-inf never), column j
    for source bit seen_bits[j]; shape_var (N,) m^2, shape_s (N,) s: position variance and time of the
    detection the box shape came from; confirmed (N,) bool (see the life cycle); birth_x (N, n),
    birth_p (N, n, n): the state the track was born with; velocity_prior (N,) bool: born without a
    measured velocity (two-point initialisation). seen_bits (B,) int64 is not a row column (default:
    every bit, B = SOURCE_BITS)."""

    x: np.ndarray
    p: np.ndarray
    ids: np.ndarray
    cls: np.ndarray
    z: np.ndarray
    lwh: np.ndarray
    yaw: np.ndarray
    confidence: np.ndarray
    hits: np.ndarray
    born_s: np.ndarray
    updated_s: np.ndarray
    seen_s: np.ndarray
    shape_var: np.ndarray
    shape_s: np.ndarray
    confirmed: np.ndarray
    birth_x: np.ndarray
    birth_p: np.ndarray
    velocity_prior: np.ndarray
    seen_bits: np.ndarray = field(default_factory=lambda: _ALL_BITS.copy())

    @classmethod
    def empty(cls, dim_x: int, rows: int = 0, seen_bits: np.ndarray | None = None) -> TrackTable:
        """A table of ``rows`` zeroed rows (seen_s -inf), one seen column per entry of seen_bits (default: all)."""
        bits = _ALL_BITS.copy() if seen_bits is None else np.asarray(seen_bits, np.int64)
        z1, no, count = np.zeros(rows), np.zeros(rows, bool), np.zeros(rows, np.int64)
        x, p = np.zeros((rows, dim_x)), np.zeros((rows, dim_x, dim_x))
        return cls(x, p, count, count.copy(), z1, np.zeros((rows, 3)), z1.copy(), z1.copy(), count.copy(),
                   z1.copy(), z1.copy(), np.full((rows, len(bits)), -np.inf), z1.copy(), z1.copy(), no,
                   x.copy(), p.copy(), no.copy(), bits)

    def __len__(self) -> int:
        return len(self.x)

    def take(self, index) -> TrackTable:
        return TrackTable(*(column[index] for column in self.columns()), seen_bits=self.seen_bits.copy())

    def copy(self) -> TrackTable:
        return TrackTable(*(column.copy() for column in self.columns()), seen_bits=self.seen_bits.copy())

    def append(self, other: TrackTable) -> TrackTable:
        """Rows of self, then of other (both with the same seen_bits)."""
        if not np.array_equal(self.seen_bits, other.seen_bits):
            raise ValueError("TrackTable.append needs tables with the same seen_bits")
        return TrackTable(*(np.concatenate([a, b]) for a, b in zip(self.columns(), other.columns())),
                          seen_bits=self.seen_bits.copy())

    def columns(self) -> list[np.ndarray]:
        """The row column arrays in field order (every field but seen_bits)."""
        return [getattr(self, name) for name in _ROW_COLUMNS]

    def source_masks(self, recent: np.ndarray) -> np.ndarray:
        """(N,) int64 bitmasks of the sources marked in recent (N, B) bool (columns as seen_s): the sum of the
        marked columns' bit values, as a product of bool (N, B) and int64 (B,) (exact: distinct bits, no carry)."""
        return recent @ (np.int64(1) << self.seen_bits)


_ROW_COLUMNS = tuple(f.name for f in fields(TrackTable) if f.name != "seen_bits")


class TrackStore:
    """Live tracks in the first n rows of preallocated columns (module docstring)."""

    def __init__(self, dim_x: int):
        self._dim_x = dim_x
        self._rows = TrackTable.empty(dim_x, 0, np.zeros(0, np.int64))
        self.n = 0
        self.view = self._rows
        self._bits_changed()

    def load(self, table: TrackTable) -> None:
        """Replace the contents by a copy of table."""
        n = len(table)
        self._rows = TrackTable.empty(self._dim_x, max(_MIN_CAPACITY, 2 * n), table.seen_bits)
        for dst, src in zip(self._rows.columns(), table.columns()):
            dst[:n] = src
        self.n = n
        self._refresh()
        self._bits_changed()

    def snapshot(self) -> TrackTable:
        """A compact copy of the live rows."""
        return self.view.copy()

    def source_columns(self, masks: np.ndarray, extra: int = 0) -> tuple[np.ndarray, int]:
        """(K, B) bool: which seen columns each of K int64 bitmasks (masks | extra) sets, and the OR of the
        masks; bits not yet in use get a column; negative masks (bit 63) are refused (ValueError)."""
        masks = np.asarray(masks, dtype=np.int64)
        cols, union = _mask_columns(masks, extra, self.col_values)
        if union < 0:  # the OR has bit 63 (the sign) exactly when some mask has it
            raise ValueError(f"source bitmasks must be in [0, 2^{SOURCE_BITS}), got {(masks | extra).min()}")
        if union & ~self._known:
            self._add_seen_bits([b for b in range(SOURCE_BITS) if (union >> b) & 1 and not (self._known >> b) & 1])
            cols, union = _mask_columns(masks, extra, self.col_values)
        return cols, union

    def append(self, new: TrackTable) -> None:
        """Add the rows of new (its seen_s columns as this store's seen_bits) after the live ones."""
        rows, added = self.extend(len(new))
        for dst, src in zip(rows.columns(), new.columns()):
            dst[added] = src

    def extend(self, k: int) -> tuple[TrackTable, slice]:
        """Make k more rows live (after the others): the store's columns (every allocated row) and the
        slice of the k new rows in them, for the caller to fill."""
        if self.n + k > len(self._rows):
            self._grow(self.n + k)
        n, self.n = self.n, self.n + k
        self._refresh()
        return self._rows, slice(n, n + k)

    def keep(self, mask: np.ndarray) -> None:
        """Keep the live rows where mask (n,) is True, in order (moved down in place)."""
        index = np.flatnonzero(mask)
        m = len(index)
        for column in self._rows.columns():
            column[:m] = column.take(index, axis=0)
        self.n = m
        self._refresh()

    def _grow(self, rows: int) -> None:
        old, n = self._rows, self.n
        self._rows = TrackTable.empty(self._dim_x, max(_MIN_CAPACITY, 2 * rows), old.seen_bits)
        for dst, src in zip(self._rows.columns(), old.columns()):
            dst[:n] = src[:n]

    def _add_seen_bits(self, bits: list[int]) -> None:
        old = self._rows
        seen = np.full((len(old), old.seen_s.shape[1] + len(bits)), -np.inf)
        seen[:, :old.seen_s.shape[1]] = old.seen_s
        old.seen_s, old.seen_bits = seen, np.concatenate([old.seen_bits, np.asarray(bits, np.int64)])
        self._refresh()
        self._bits_changed()

    def _bits_changed(self) -> None:
        self.col_values = np.int64(1) << self._rows.seen_bits  # (B,) the bit value of each seen column
        self._known = int(np.bitwise_or.reduce(self.col_values)) if len(self.col_values) else 0  # bits with a column

    def _refresh(self) -> None:
        # the TrackTable of views built in C (map / itemgetter / dict update) rather than through the dataclass
        # __init__ and a generator: this runs on every spawn and prune
        rows, view = self._rows, TrackTable.__new__(TrackTable)
        live = map(itemgetter(slice(0, self.n)), map(rows.__dict__.__getitem__, _ROW_COLUMNS))
        view.__dict__.update(zip(_ROW_COLUMNS, live))
        view.seen_bits = rows.seen_bits
        self.view = view


@kernel(IN_I1, I64, IN_I1)
def _mask_columns(masks, extra, col_values):
    """cols (K, B): (masks[k] | extra) & col_values[b] != 0 (the seen columns each of K bitmasks sets, column b
    standing for the bit value col_values[b]) and the OR of the K masks with extra (0 for K = 0: no column)."""
    cols = np.empty((len(masks), len(col_values)), np.bool_)
    union = extra if len(masks) else 0
    for k in range(len(masks)):
        mask = masks[k] | extra
        union |= mask
        for b in range(len(col_values)):
            cols[k, b] = (mask & col_values[b]) != 0
    return cols, union


@kernel(OUT_I1, OUT_F1, OUT_F2, OUT_F1, OUT_F1, OUT_F1, OUT_F1, OUT_I1, OUT_B1, OUT_F1, OUT_F2,
        IN_I1, IN_I1, IN_I1, IN_F1, IN_F2, IN_F1, IN_F3, IN_F1, IN_B2, F64, B1, I64, F64)
def record_matches(cls, z, lwh, yaw, shape_var, shape_s, confidence, hits, confirmed, updated_s, seen_s,
                   ti, di, det_cls, det_z, det_lwh, det_yaw, det_cov_xy, det_confidence, det_cols, t_s, estimates,
                   confirm_hits, shape_hold_s) -> None:
    """The bookkeeping of tracks ti (distinct rows of the TrackTable columns cls .. seen_s, in place)
    matched with detections di at t_s: an UNKNOWN class (0) adopts the detection's; the box (z, lwh,
    yaw; the heading det_yaw wrapped to [-pi, pi) as ``frames.wrap_angle``) comes from the detection when
    its position variance (trace of det_cov_xy) is no larger (1 % slack) or the track's box is older than
    shape_hold_s; confidence; hits + 1; confirmed (always, for another tracker's estimates, else at
    confirm_hits hits); updated_s; seen_s = t_s in the columns det_cols (M, B) marks for the detection's sources."""
    for k in range(len(ti)):
        i, j = ti[k], di[k]
        if cls[i] == 0:
            cls[i] = det_cls[j]
        var = det_cov_xy[j, 0, 0] + det_cov_xy[j, 1, 1]
        if var <= shape_var[i] * 1.01 or t_s - shape_s[i] > shape_hold_s:
            # (yaw + pi) mod 2 pi - pi: numba's float % is numpy's remainder (fmod, then the divisor's sign)
            z[i], yaw[i], shape_var[i], shape_s[i] = det_z[j], (det_yaw[j] + np.pi) % (2.0 * np.pi) - np.pi, var, t_s
            lwh[i, 0], lwh[i, 1], lwh[i, 2] = det_lwh[j, 0], det_lwh[j, 1], det_lwh[j, 2]
        confidence[i] = det_confidence[j]
        hits[i] += 1
        confirmed[i] = estimates or confirmed[i] or hits[i] >= confirm_hits
        updated_s[i] = t_s
        for b in range(seen_s.shape[1]):
            if det_cols[j, b]:
                seen_s[i, b] = t_s


@kernel(IN_F2, IN_I1, IN_B2, IN_I1, IN_I1, I64, F64, F64)
def estimate_rules(seen_s, ti, det_cols, di, col_values, intersecting_mask, t_s, max_coast_s):
    """The fusion rule of each pair (track ti[k], estimate di[k]) (``v2i.fusion.tracking``'s module docstring), from
    the sources outside the estimate's bits (det_cols (M, B) False) that updated the track within max_coast_s
    (t_s - seen_s <= max_coast_s): none: rule 1 (alone); one whose column value (col_values (B,)) has a bit
    of intersecting_mask: rule 2 (intersect); else rule 3. Returns (order (K,), n_alone, n_intersect):
    the pair indices of rule 1, then rule 2, then rule 3, each group in pair order."""
    n = len(ti)
    rule = np.zeros(n, np.int64)
    count = np.zeros(3, np.int64)
    for k in range(n):
        i, j = ti[k], di[k]
        for b in range(seen_s.shape[1]):
            if not det_cols[j, b] and t_s - seen_s[i, b] <= max_coast_s:  # another source, recently
                if col_values[b] & intersecting_mask:
                    rule[k] = 1
                    break
                rule[k] = 2
        count[rule[k]] += 1
    order = np.empty(n, np.int64)
    start = np.array([0, count[0], count[0] + count[1]])
    for k in range(n):
        order[start[rule[k]]] = k
        start[rule[k]] += 1
    return order, count[0], count[1]


def estimate_rules_reference(seen_s, ti, cols, di, col_values, mask, t_s, max_coast_s):
    """``estimate_rules`` by numpy expressions (Tracker.update's before the kernel; its plain reference: on the
    calls of 330 cycle_compute cycles 15.4 us per call against the kernel's 3.1 us)."""
    other = ((t_s - seen_s.take(ti, axis=0)) <= max_coast_s) & ~cols.take(di, axis=0)
    shared_any = np.logical_or.reduce(other, axis=1)
    shared = np.logical_or.reduce(other & ((col_values & mask) != 0), axis=1)
    alone, ci = np.flatnonzero(~shared_any), np.flatnonzero(shared_any & shared)
    rest = np.flatnonzero(shared_any & ~shared)
    return np.concatenate([alone, ci, rest]), len(alone), len(ci)


def mask_columns_reference(masks, extra, col_values):
    """``_mask_columns`` by numpy expressions (its plain reference: on the calls of 330 cycle_compute cycles
    9.3 us per call against the kernel's 1.1 us)."""
    m = masks | extra
    return (m[:, None] & col_values[None, :]) != 0, int(np.bitwise_or.reduce(m)) if len(m) else 0


def record_matches_reference(cls, z, lwh, yaw, shape_var, shape_s, confidence, hits, confirmed, updated_s, seen_s,
                             ti, di, det_cls, det_z, det_lwh, det_yaw, det_cov_xy, det_confidence, det_cols, t_s,
                             estimates, confirm_hits, shape_hold_s) -> None:
    """``record_matches`` by numpy expressions over the K pairs at once (its plain reference: on the calls of 330
    cycle_compute cycles 68 us per call against the kernel's 12 us)."""
    cls[ti] = np.where(cls[ti] == 0, det_cls[di], cls[ti])
    var = det_cov_xy[di, 0, 0] + det_cov_xy[di, 1, 1]
    take = (var <= shape_var[ti] * 1.01) | (t_s - shape_s[ti] > shape_hold_s)
    t, d = ti[take], di[take]
    z[t], yaw[t], lwh[t] = det_z[d], (det_yaw[d] + np.pi) % (2.0 * np.pi) - np.pi, det_lwh[d]
    shape_var[t], shape_s[t] = var[take], t_s
    confidence[ti] = det_confidence[di]
    hits[ti] += 1
    confirmed[ti] = estimates | confirmed[ti] | (hits[ti] >= confirm_hits)
    updated_s[ti] = t_s
    seen_s[ti] = np.where(det_cols[di], t_s, seen_s[ti])
