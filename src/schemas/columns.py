"""Object lists as columns of quantisation codes, validated as arrays.

An :class:`ObjectColumns` holds N objects as one ``(N, K)`` int64 matrix of codes, one column
per wire attribute (``OBJECT_SPECS``; fused lists add ``sources``). The rules are those of the
per-object models :class:`~schemas.object_state.ObjectState` / ``FusedObject`` (same ranges, same
grids, same round-half-even quantisation, yaw wrapped into [-pi, pi)), applied to whole columns:
a value ``v`` of a grid column is accepted iff it is finite and inside the column's bounds, and
becomes ``k * step`` with ``k = rint(v / step)``. A failure is an ``InvalidMessage`` whose
``field`` names the first offending object and column (``objects.3.x``), as pydantic did.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np

from schemas import limits as m
from schemas import quantize as q
from schemas.classes import ObjectClass
from schemas.errors import InvalidMessage

if TYPE_CHECKING:
    from schemas.object_state import ObjectState

_INT, _GRID, _YAW = "int", "grid", "yaw"
_YAW_HALF_TURN = round(math.pi / q.YAW_RAD)  # 1800 codes: yaw codes live in [-1800, 1800)


@dataclass(frozen=True)
class Spec:
    """One object attribute: ``kind`` int / grid / yaw, value bounds ``lo <= v <= hi``,
    ``step`` (1 for integers), ``default`` value (None: required)."""

    name: str
    kind: str
    lo: float
    hi: float
    step: float = 1.0
    default: float | None = None

    @property
    def code_bounds(self) -> tuple[int, int]:
        """Smallest and largest code whose value ``code * step`` lies inside [lo, hi] (the very
        float comparison pydantic makes on the decoded value)."""
        if self.kind == _INT:
            return int(self.lo), int(self.hi)
        lo, hi = math.ceil(self.lo / self.step) - 1, math.floor(self.hi / self.step) + 1
        while lo * self.step < self.lo:
            lo += 1
        while hi * self.step > self.hi:
            hi -= 1
        return lo, hi

    @property
    def default_code(self) -> int | None:
        if self.default is None:
            return None
        return round(self.default / self.step)


def _grid(name: str, bound: float, step: float, default: float | None = None, lo: float | None = None) -> Spec:
    return Spec(name, _GRID, -bound if lo is None else lo, bound, step, default)


OBJECT_SPECS: tuple[Spec, ...] = (
    Spec("id", _INT, 0, 2**32 - 1),
    Spec("cls", _INT, min(ObjectClass), max(ObjectClass), default=ObjectClass.UNKNOWN),
    _grid("x", m.POSITION_MAX_M, q.POSITION_M),
    _grid("y", m.POSITION_MAX_M, q.POSITION_M),
    _grid("z", m.HEIGHT_MAX_M, q.POSITION_M, 0.0),
    _grid("length", m.SIZE_MAX_M, q.SIZE_M, lo=0.0),
    _grid("width", m.SIZE_MAX_M, q.SIZE_M, lo=0.0),
    _grid("height", m.SIZE_MAX_M, q.SIZE_M, 1.5, lo=0.0),
    Spec("yaw", _YAW, -100.0, 100.0, q.YAW_RAD, 0.0),
    _grid("vx", m.SPEED_MAX_MPS, q.SPEED_MPS, 0.0),
    _grid("vy", m.SPEED_MAX_MPS, q.SPEED_MPS, 0.0),
    _grid("ax", m.ACCEL_MAX_MPS2, q.ACCEL_MPS2, 0.0),
    _grid("ay", m.ACCEL_MAX_MPS2, q.ACCEL_MPS2, 0.0),
    _grid("yaw_rate", m.YAW_RATE_MAX, q.YAW_RATE_RADPS, 0.0),
    _grid("cov_xx", m.VARIANCE_MAX, q.COV_M2, 1.0, lo=0.0),
    _grid("cov_xy", m.VARIANCE_MAX, q.COV_M2, 0.0),
    _grid("cov_yy", m.VARIANCE_MAX, q.COV_M2, 1.0, lo=0.0),
    _grid("cov_vxx", m.VARIANCE_MAX, q.COV_M2, m.UNKNOWN_VELOCITY_VAR, lo=0.0),
    _grid("cov_vxy", m.VARIANCE_MAX, q.COV_M2, 0.0),
    _grid("cov_vyy", m.VARIANCE_MAX, q.COV_M2, m.UNKNOWN_VELOCITY_VAR, lo=0.0),
    _grid("confidence", 1.0, q.CONFIDENCE, 1.0, lo=0.0),
    _grid("age_s", m.AGE_MAX_S, q.AGE_S, 0.0, lo=0.0),
)
FUSED_SPECS: tuple[Spec, ...] = (*OBJECT_SPECS, Spec("sources", _INT, 0, 255, default=m.SOURCE_VEHICLE))
COLUMN = {s.name: j for j, s in enumerate(FUSED_SPECS)}  # name -> column index (same in both layouts)


@dataclass(frozen=True)
class Layout:
    """Per-column arrays of one spec tuple, for vectorised checks."""

    specs: tuple[Spec, ...]

    @cached_property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.specs)

    @cached_property
    def steps(self) -> np.ndarray:
        return np.array([s.step for s in self.specs])

    @cached_property
    def lo(self) -> np.ndarray:
        return np.array([s.lo for s in self.specs])

    @cached_property
    def hi(self) -> np.ndarray:
        return np.array([s.hi for s in self.specs])

    @cached_property
    def code_lo(self) -> np.ndarray:
        return np.array([s.code_bounds[0] for s in self.specs], dtype=np.int64)

    @cached_property
    def code_hi(self) -> np.ndarray:
        return np.array([s.code_bounds[1] for s in self.specs], dtype=np.int64)

    @cached_property
    def integer(self) -> np.ndarray:
        return np.array([s.kind == _INT for s in self.specs])

    @cached_property
    def required(self) -> np.ndarray:
        return np.array([s.default is None for s in self.specs])

    @cached_property
    def default_codes(self) -> np.ndarray:
        """(K,) default code per column (0 where the column is required)."""
        return np.array([s.default_code or 0 for s in self.specs], dtype=np.int64)

    @cached_property
    def required_mask(self) -> int:
        """The required columns as a present mask (bit j: column j)."""
        return sum(1 << j for j, s in enumerate(self.specs) if s.default is None)

    @cached_property
    def value_table(self) -> np.ndarray:
        """(4, K) float64: ``lo``, ``hi``, ``steps``, ``integer`` (1.0: integer): the argument of
        ``schemas.bit_rows.quantize_values``."""
        out = np.array([self.lo, self.hi, self.steps, self.integer], dtype=np.float64)
        out.flags.writeable = False
        return out

    @cached_property
    def code_table(self) -> np.ndarray:
        """(4, K) int64: ``default_codes``, ``code_lo``, ``code_hi``, ``required`` (1: required): one
        argument of the codec's compiled loops (``schemas.bit_rows``)."""
        out = np.array([self.default_codes, self.code_lo, self.code_hi, self.required], dtype=np.int64)
        out.flags.writeable = False
        return out


OBJECTS, FUSED = Layout(OBJECT_SPECS), Layout(FUSED_SPECS)
_YAW_COL = COLUMN["yaw"]
_compiled_values = None  # schemas.bit_rows.quantize_values, once loaded (v2i.core.jit.load_kernels)


def use_compiled(quantize_values) -> None:
    """From now on ``ObjectColumns.from_values`` checks and quantises with ``schemas.bit_rows.quantize_values``."""
    global _compiled_values
    _compiled_values = quantize_values


def layout_of(fused: bool) -> Layout:
    return FUSED if fused else OBJECTS


def _first_bad(ok: np.ndarray, values: np.ndarray, layout: Layout, what: str) -> InvalidMessage:
    """InvalidMessage at the first False of ``ok`` (N, K) in object-then-column order."""
    i, j = divmod(int(np.flatnonzero(~ok.ravel())[0]), ok.shape[1])
    spec = layout.specs[j]
    return InvalidMessage(f"objects.{i}.{spec.name} = {values[i, j]!r} {what} "
                          f"[{spec.lo:g}, {spec.hi:g}]{'' if spec.kind == _INT else f' (step {spec.step:g})'}",
                          f"objects.{i}.{spec.name}")


def _canonical_yaw(codes: np.ndarray) -> np.ndarray:
    """Yaw codes wrapped into [-1800, 1800): ``object_state._yaw`` on each value ``k * step``
    (wrap to [-pi, pi), re-quantise, fold 1800 onto -1800), vectorised."""
    outside = (codes < -_YAW_HALF_TURN) | (codes >= _YAW_HALF_TURN)
    if not outside.any():
        return codes
    values = codes * q.YAW_RAD
    k = np.rint((np.mod(values + math.pi, 2.0 * math.pi) - math.pi) / q.YAW_RAD).astype(np.int64)
    k = np.where(k >= _YAW_HALF_TURN, k - 2 * _YAW_HALF_TURN, k)
    return np.where(outside, k, codes)


class ObjectColumns:
    """N validated objects as codes: ``codes`` (N, K) int64, K = 22 (23 with ``sources`` when
    ``fused``); ``values`` (N, K) float64 = codes * step (metres, m/s, rad, ...). Immutable.

    Build it with :meth:`from_values` (floats, checked and quantised), :meth:`from_codes`
    (wire codes, checked) or :meth:`from_states` (per-object models or dicts: small inputs).
    """

    __slots__ = ("codes", "fused", "__dict__")

    def __init__(self, codes: np.ndarray, fused: bool) -> None:
        """Trusted constructor: ``codes`` already valid and canonical (use the ``from_*`` builders)."""
        codes.flags.writeable = False
        self.codes, self.fused = codes, fused

    # ------------------------------------------------------------ builders
    @classmethod
    def empty(cls, fused: bool = False) -> ObjectColumns:
        return cls(np.zeros((0, len(layout_of(fused).specs)), np.int64), fused)

    @classmethod
    def from_values(cls, table: np.ndarray, fused: bool = False) -> ObjectColumns:
        """Objects from an (N, K) float table in ``layout_of(fused).names`` order: every value
        checked against its column's range (finite, integers integral) and quantised."""
        layout = layout_of(fused)
        table = np.asarray(table, dtype=np.float64)
        if table.ndim != 2 or table.shape[1] != len(layout.specs):
            raise InvalidMessage(f"objects: expected an (N, {len(layout.specs)}) table, got shape {table.shape}",
                                 "objects")
        _check_count(len(table))
        if _compiled_values is not None:  # one compiled loop; a table it refuses goes on for the very error
            codes, bad = _compiled_values(table, layout.value_table, _YAW_COL)
            if bad < 0:
                return cls(codes, fused)
        ok = np.isfinite(table) & (table >= layout.lo) & (table <= layout.hi)
        with np.errstate(invalid="ignore"):
            codes_f = np.rint(table / layout.steps)
            ok &= ~layout.integer | (codes_f == table)  # integer attributes must be integers
        if not ok.all():
            raise _first_bad(ok, table, layout, "is not a number inside")
        codes = codes_f.astype(np.int64)
        yaw = table[:, _YAW_COL]
        k = np.rint((np.mod(yaw + math.pi, 2.0 * math.pi) - math.pi) / q.YAW_RAD).astype(np.int64)
        codes[:, _YAW_COL] = np.where(k >= _YAW_HALF_TURN, k - 2 * _YAW_HALF_TURN, k)
        return cls(codes, fused)

    @classmethod
    def from_codes(cls, codes: np.ndarray, fused: bool = False) -> ObjectColumns:
        """Objects from (N, K) int64 wire codes: each code's value ``code * step`` checked
        against its column's range, yaw codes wrapped as the model wraps their values."""
        layout = layout_of(fused)
        _check_count(len(codes))
        ok = (codes >= layout.code_lo) & (codes <= layout.code_hi)
        if not ok.all():
            raise _first_bad(ok, codes * layout.steps, layout, "is outside")
        yaw = codes[:, _YAW_COL]
        canonical = _canonical_yaw(yaw)
        if canonical is not yaw:
            codes = codes.copy()
            codes[:, _YAW_COL] = canonical
        return cls(codes, fused)

    @classmethod
    def from_states(cls, states: Sequence[Any], fused: bool = False) -> ObjectColumns:
        """Objects from per-object models (``ObjectState``/``FusedObject``) or their dicts,
        each validated by its model (a loop: for small, hand-made lists)."""
        if isinstance(states, ObjectColumns):
            return states.as_fused(fused)
        from schemas.object_state import FusedObject, ObjectState

        model = FusedObject if fused else ObjectState
        _check_count(len(states))
        rows = [s if isinstance(s, ObjectState) else model.model_validate(s) for s in states]
        names = layout_of(fused).names
        table = np.array([[float(getattr(r, n, m.SOURCE_VEHICLE)) for n in names] for r in rows], dtype=np.float64)
        return cls.from_values(table.reshape(len(rows), len(names)), fused)

    def as_fused(self, fused: bool) -> ObjectColumns:
        """The same objects in the other layout: ``sources`` added (SOURCE_VEHICLE) or dropped."""
        if fused == self.fused:
            return self
        if fused:
            codes = np.column_stack([self.codes, np.full(len(self), m.SOURCE_VEHICLE, np.int64)])
        else:
            codes = self.codes[:, :-1].copy()
        return ObjectColumns(codes, fused)

    # ------------------------------------------------------------ access
    @cached_property
    def values(self) -> np.ndarray:
        """(N, K) float64: code * step (ids, classes and sources as exact floats)."""
        out = self.codes * layout_of(self.fused).steps
        out.flags.writeable = False
        return out

    @property
    def names(self) -> tuple[str, ...]:
        return layout_of(self.fused).names

    @property
    def ids(self) -> np.ndarray:
        return self.codes[:, COLUMN["id"]]

    def column(self, name: str) -> np.ndarray:
        """(N,) values of one attribute (int64 for id, cls and sources)."""
        j = COLUMN[name]
        return self.codes[:, j] if layout_of(self.fused).integer[j] else self.values[:, j]

    def row(self, i: int) -> ObjectState:
        """Object ``i`` as its model (``FusedObject`` when fused): convenient, not fast."""
        from schemas.object_state import FusedObject, ObjectState

        model = FusedObject if self.fused else ObjectState
        integer = layout_of(self.fused).integer
        kw = {n: int(c) if integer[j] else float(v)
              for j, (n, c, v) in enumerate(zip(self.names, self.codes[i], self.values[i]))}
        return model.model_validate(kw)  # values on the grid already: validation keeps them

    def __len__(self) -> int:
        return len(self.codes)

    def __getitem__(self, i: int) -> ObjectState:
        if not -len(self) <= i < len(self):
            raise IndexError(f"object {i} of {len(self)}")
        return self.row(i % len(self))

    def __iter__(self) -> Iterator[ObjectState]:
        return (self.row(i) for i in range(len(self)))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ObjectColumns):
            return NotImplemented
        return self.fused == other.fused and np.array_equal(self.codes, other.codes)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"ObjectColumns({len(self)} objects{', fused' if self.fused else ''})"


def _check_count(n: int) -> None:
    if n > m.MAX_OBJECTS:
        raise InvalidMessage(f"objects: {n} objects, at most {m.MAX_OBJECTS} allowed", "objects")


def objects_field(fused: bool):
    """Pydantic validator of a message's ``objects``: an ObjectColumns (re-laid out if needed)
    or a sequence of per-object models / dicts."""

    def validate(value: Any) -> ObjectColumns:
        if isinstance(value, ObjectColumns):
            if value.fused != fused and not fused:
                raise ValueError("objects carry sources; only fused lists have them")
            return value.as_fused(fused)
        if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
            raise ValueError(f"objects must be ObjectColumns or a sequence of objects, got {type(value).__name__}")
        return ObjectColumns.from_states(value, fused)

    return validate
