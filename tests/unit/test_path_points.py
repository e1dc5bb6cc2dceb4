"""PredictedPath's array fast path (schemas.path_points) accepts, rejects and grids exactly as
the per-point models do: values bit for bit, errors field for field."""

from __future__ import annotations

import math
import struct
from typing import Annotated

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import Field, TypeAdapter, ValidationError, model_validator

from schemas import quantize as q
from schemas.limits import MAX_OBJECTS, POSITION_MAX_M
from schemas.messages import (
    MAX_PATH_POINTS,
    Message,
    Position,
    PredictedPath,
    PredictionList,
    Yaw,
    _path,
    predicted_paths,
)
from schemas.object_state import _yaw
from schemas.path_points import grid_positions, grid_yaws, paths_from_dicts


class PerPointPath(Message):
    """PredictedPath as it was: each point validated and gridded by its own Position / Yaw."""

    id: Annotated[int, Field(ge=0, lt=2**32)]
    x: Annotated[tuple[Position, ...], Field(max_length=MAX_PATH_POINTS)] = ()
    y: Annotated[tuple[Position, ...], Field(max_length=MAX_PATH_POINTS)] = ()
    yaw: Annotated[tuple[Yaw, ...], Field(max_length=MAX_PATH_POINTS)] = ()

    @model_validator(mode="after")
    def _same_lengths(self) -> PerPointPath:
        if not len(self.x) == len(self.y) == len(self.yaw):
            raise ValueError(f"x, y and yaw must have one entry per step, got {len(self.x)}, {len(self.y)}, {len(self.yaw)}")
        return self


def _bits(values) -> list[bytes]:
    return [struct.pack("<d", v) for v in values]  # -0.0 and 0.0 differ here


def _outcome(model: type, fields: dict):
    try:
        path = model(id=3, **fields)
    except ValidationError as exc:
        return "error", [(e["type"], e["loc"], e["msg"]) for e in exc.errors(include_url=False)]
    assert all(type(v) is float for v in path.x + path.y + path.yaw)
    return "ok", (_bits(path.x), _bits(path.y), _bits(path.yaw))


_FINITE = st.floats(-2e6, 2e6, allow_nan=False)
_POINT = st.one_of(_FINITE, st.floats(-1e4, 1e4), st.floats(), st.sampled_from([0.0, -0.0, -0.004, 0.005, -0.005, 0.015,
                                                                                  math.pi, -math.pi, 3.14159, 99.9, -100.0,
                                                                                  1e6, -1e6, 1e6 + 0.001, 100.0001]))
_ODD = st.one_of(st.integers(-20_000, 20_000), st.booleans(), st.just("1.5"), st.none(), st.just(np.float64(0.5)))


@st.composite
def _fields(draw) -> dict:
    n = draw(st.one_of(st.integers(0, 8), st.just(MAX_PATH_POINTS), st.just(MAX_PATH_POINTS + 1)))
    fields = {}
    for name in ("x", "y", "yaw"):
        points = draw(st.lists(_POINT, min_size=n, max_size=n))
        if points and draw(st.integers(0, 9)) == 0:  # now and then one point of another type
            points[draw(st.integers(0, len(points) - 1))] = draw(_ODD)
        fields[name] = tuple(points) if draw(st.booleans()) else points
    return fields


@settings(max_examples=400, deadline=None)
@given(_fields())
def test_fast_path_equals_per_point_models(fields) -> None:
    assert _outcome(PredictedPath, fields) == _outcome(PerPointPath, fields)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e4, 1e4, allow_nan=False), max_size=64))
def test_grids_equal_the_scalar_functions(values) -> None:
    a = np.array(values, dtype=np.float64)
    assert _bits(grid_positions(a).tolist()) == _bits([q.quantize(v, q.POSITION_M) for v in values])
    assert _bits(grid_yaws(a).tolist()) == _bits([_yaw(v) for v in values])


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), 1e6 + 0.5, "x"])
def test_a_bad_point_still_names_its_index(bad) -> None:
    with pytest.raises(ValidationError) as info:
        PredictedPath(id=1, x=[1.0, 2.0, bad], y=[0.0] * 3, yaw=[0.0] * 3)
    assert info.value.errors()[0]["loc"] == ("x", 2)


_PATHS_FIELD = PredictionList.model_fields["paths"]
_paths_adapter = TypeAdapter(Annotated[(_PATHS_FIELD.annotation, *_PATHS_FIELD.metadata)])  # the field's validation


def _path_bits(paths) -> list:
    return [(p.id, _bits(p.x), _bits(p.y), _bits(p.yaw), sorted(p.model_fields_set)) for p in paths]


@st.composite
def _path_dicts(draw) -> list:
    n_paths, n_points = draw(st.integers(0, 5)), draw(st.integers(0, 6))
    dicts = []
    for _ in range(n_paths):
        d = {"id": draw(st.one_of(st.integers(0, 2**32 - 1), st.sampled_from([-1, 2**32, True, 1.0]))),
             **{k: draw(st.lists(_POINT, min_size=n_points, max_size=n_points)) for k in ("x", "y", "yaw")}}
        if draw(st.integers(0, 9)) == 0:
            d[draw(st.sampled_from(["x", "y", "yaw"]))].append(0.0)  # unequal lengths
        if draw(st.integers(0, 19)) == 0:
            del d["yaw"]
        dicts.append(d)
    return dicts


def _check_fast_paths(dicts, must_take: bool = False):
    """paths_from_dicts(dicts) against the model path by path: None where the model rejects a path
    (then the fast check must too), else bit-equal values wherever it takes them (must_take: it does);
    returns the model's paths (None when rejected)."""
    fast = paths_from_dicts(dicts, MAX_OBJECTS, MAX_PATH_POINTS, POSITION_MAX_M, 100.0)
    try:
        reference = [PredictedPath.model_validate(d) for d in dicts]
    except ValidationError:
        assert fast is None
        return None
    assert fast is not None or not must_take
    if fast is not None:
        assert [(i, _bits(x), _bits(y), _bits(yaw)) for i, x, y, yaw in fast] == [r[:4] for r in _path_bits(reference)]
    return reference


@settings(max_examples=300, deadline=None)
@given(_path_dicts())
def test_decoded_paths_fast_path_equals_path_by_path(dicts) -> None:
    """A PredictionList's paths from dicts: the one-pass check accepts only what the model
    accepts, with bit-equal values and the same fields set."""
    reference = _check_fast_paths(dicts)
    if reference is not None:
        assert _path_bits(_paths_adapter.validate_python(dicts)) == _path_bits(reference)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 6), st.integers(0, 8), st.data())
def test_predicted_paths_equal_path_by_path_construction(n, k, data) -> None:
    values = st.one_of(st.floats(-2e6, 2e6), st.floats(-150.0, 150.0))
    points = np.array(data.draw(st.lists(values, min_size=n * k * 3, max_size=n * k * 3)), dtype=float).reshape(n, k, 3)
    ids = np.array(data.draw(st.lists(st.integers(0, 2**32 - 1), min_size=n, max_size=n)), dtype=np.int64)

    def one_by_one():
        return tuple(PredictedPath(id=int(i), x=p[:, 0].tolist(), y=p[:, 1].tolist(), yaw=p[:, 2].tolist())
                     for i, p in zip(ids, points))
    try:
        reference = one_by_one()
    except ValidationError as exc:
        with pytest.raises(ValidationError) as info:
            predicted_paths(ids, points)
        assert info.value.errors(include_url=False) == exc.errors(include_url=False)
        return
    assert _path_bits(predicted_paths(ids, points)) == _path_bits(reference)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(0, 7), max_size=6), st.data())
def test_decoded_paths_of_different_lengths_equal_path_by_path(lengths, data) -> None:
    """Paths of unequal lengths (each path's x, y, yaw alike) take the sliced split, equal
    lengths the reshaped one: both give each path's own values, bit for bit."""
    values = st.one_of(st.floats(-2e6, 2e6, allow_nan=False), st.floats(-150.0, 150.0))
    dicts = [{"id": j, **{k: data.draw(st.lists(values, min_size=n, max_size=n)) for k in ("x", "y", "yaw")}}
             for j, n in enumerate(lengths)]
    _check_fast_paths(dicts, must_take=True)


def test_fast_path_object_is_model_construct() -> None:
    """messages._path builds what PredictedPath.model_construct builds: fields, fields set,
    no extra, no private attributes; equal, hashed alike, dumped alike, still frozen."""
    x, y, yaw = (1.0, 2.5), (0.0, -3.25), (0.1, 3.0)
    fast, reference = _path(7, x, y, yaw), PredictedPath.model_construct(id=7, x=x, y=y, yaw=yaw)
    assert type(fast) is PredictedPath
    assert fast.__dict__ == reference.__dict__ and list(fast.__dict__) == list(reference.__dict__)
    assert fast.model_fields_set == reference.model_fields_set == {"id", "x", "y", "yaw"}
    assert fast.__pydantic_extra__ is reference.__pydantic_extra__ is None
    assert fast.__pydantic_private__ is reference.__pydantic_private__ is None
    assert fast == reference and hash(fast) == hash(reference)
    assert fast.model_dump() == reference.model_dump() and fast.model_dump_json() == reference.model_dump_json()
    with pytest.raises(ValidationError):
        fast.id = 8
    assert fast.__pydantic_fields_set__ is not _path(7, x, y, yaw).__pydantic_fields_set__  # not shared
