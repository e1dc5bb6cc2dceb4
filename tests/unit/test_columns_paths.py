"""``ObjectColumns.from_values`` by ``schemas.bit_rows.quantize_values`` (once the kernels are loaded)
against its numpy path: the very codes, or the very refusal (type, message, field), for tables
inside every range, at the edges, past them, with NaN, infinities and fractional integers, and yaws
all around the circle (half-steps, multiples of pi)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas import columns
from schemas import quantize as q
from schemas.columns import FUSED, OBJECTS, ObjectColumns
from schemas.errors import CodecError

MANY = settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
YAW = columns.COLUMN["yaw"]


def outcome(table: np.ndarray, fused: bool):
    try:
        return "codes", ObjectColumns.from_values(table, fused).codes.tobytes()
    except CodecError as exc:
        return type(exc), str(exc), exc.reason, getattr(exc, "field", None)


def numpy_outcome(table: np.ndarray, fused: bool):
    saved = columns._compiled_values
    columns.use_compiled(None)
    try:
        return outcome(table, fused)
    finally:
        columns.use_compiled(saved)


@st.composite
def tables(draw):
    fused = draw(st.booleans())
    layout = FUSED if fused else OBJECTS
    n = draw(st.sampled_from([0, 1, 2, 6, 40]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    table = rng.uniform(np.maximum(layout.lo, -500.0), np.minimum(layout.hi, 500.0), size=(n, len(layout.lo)))
    table[:, layout.integer] = np.rint(table[:, layout.integer])
    turns = rng.integers(-30, 31, n) * math.pi / 10  # yaws at multiples of pi / 10, half-steps, anywhere
    table[:, YAW] = rng.choice([0, 1, 2], n).choose([turns, (rng.integers(-50000, 50000, n) + 0.5) * q.YAW_RAD,
                                                     rng.uniform(-100.0, 100.0, n)])
    if n and draw(st.integers(0, 2)) == 0:  # one bad or edge value
        i, j = draw(st.integers(0, n - 1)), draw(st.integers(0, len(layout.lo) - 1))
        table[i, j] = draw(st.sampled_from([math.nan, math.inf, -math.inf, layout.lo[j], layout.hi[j],
                                            np.nextafter(layout.hi[j], math.inf), np.nextafter(layout.lo[j], -math.inf),
                                            0.5, -0.0, 100.0, -100.0, math.pi, -math.pi]))
    return table, fused


@pytest.fixture(scope="module", autouse=True)
def kernels():
    from v2i.core.jit import load_kernels

    load_kernels(("schemas.bit_rows",))
    assert columns._compiled_values is not None


@MANY
@given(case=tables())
def test_compiled_from_values_equals_numpy(case) -> None:
    table, fused = case
    assert outcome(table, fused) == numpy_outcome(table, fused)


def test_yaw_codes_around_the_circle() -> None:
    """Every 0.05 deg from -100 rad to 100 rad (and the half-step neighbours of the wrap): the same codes."""
    yaw = np.concatenate([np.arange(-100.0, 100.0, q.YAW_RAD / 2),
                          np.nextafter(np.arange(-31, 32) * math.pi, math.inf), np.arange(-31, 32) * math.pi])
    yaw = yaw[np.abs(yaw) <= 100.0]
    table = np.zeros((len(yaw), len(OBJECTS.lo)))
    table[:, [columns.COLUMN["length"], columns.COLUMN["width"]]] = 4.0
    table[:, YAW] = yaw
    for start in range(0, len(yaw), 1000):
        chunk = table[start:start + 1000]
        assert outcome(chunk, False) == numpy_outcome(chunk, False)
