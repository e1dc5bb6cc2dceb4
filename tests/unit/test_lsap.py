"""``fusion.lsap.linear_sum_assignment`` (compiled) against ``scipy.optimize.linear_sum_assignment``:
the same pairs, in the same order, also where costs tie (small integers, constant matrices), with
infinite entries, wide and tall, and the same ValueErrors."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize

from fusion.lsap import linear_sum_assignment


def _same(cost: np.ndarray, maximize: bool = False) -> None:
    want = scipy.optimize.linear_sum_assignment(cost, maximize=maximize)
    got = linear_sum_assignment(cost, maximize=maximize)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert got[0].dtype == got[1].dtype == np.int64


def _random_costs(seed: int):
    rng = np.random.default_rng(seed)
    n, m = rng.integers(0, 9, size=2)
    kind = seed % 4
    if kind == 0:
        return rng.normal(size=(n, m)) * 10
    if kind == 1:  # many ties
        return rng.integers(0, 3, size=(n, m)).astype(float)
    if kind == 2:  # gated: a large cost outside the gate, as the tracker and the scorers use it
        cost = rng.uniform(0, 5, size=(n, m))
        return np.where(rng.random((n, m)) < 0.6, 1e12, cost)
    cost = rng.uniform(-1, 1, size=(n, m))  # some pairs forbidden (+inf), still feasible or not
    return np.where(rng.random((n, m)) < 0.3, np.inf, cost)


@pytest.mark.parametrize("seed", range(400))
def test_the_same_matching_as_scipy(seed):
    cost = _random_costs(seed)
    try:
        want = scipy.optimize.linear_sum_assignment(cost)
    except ValueError as exc:
        with pytest.raises(ValueError, match=str(exc)):
            linear_sum_assignment(cost)
        return
    got = linear_sum_assignment(cost)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


@pytest.mark.parametrize("shape", [(1, 1), (1, 6), (6, 1), (5, 5), (3, 7), (7, 3), (40, 60), (60, 40)])
def test_constant_and_large_matrices(shape):
    _same(np.zeros(shape))
    _same(np.full(shape, 3.0), maximize=True)
    _same(np.random.default_rng(sum(shape)).integers(0, 4, size=shape).astype(float), maximize=True)
    _same(np.random.default_rng(7).exponential(size=shape))


def test_empty_and_one_sided():
    for shape in [(0, 0), (0, 4), (4, 0)]:
        rows, cols = linear_sum_assignment(np.zeros(shape))
        assert len(rows) == len(cols) == 0


@pytest.mark.parametrize("bad, maximize", [(np.nan, False), (-np.inf, False), (np.inf, True)])
def test_invalid_entries_are_refused(bad, maximize):
    cost = np.ones((3, 3))
    cost[1, 2] = bad
    with pytest.raises(ValueError, match="invalid numeric entries"):
        scipy.optimize.linear_sum_assignment(cost, maximize=maximize)
    with pytest.raises(ValueError, match="invalid numeric entries"):
        linear_sum_assignment(cost, maximize=maximize)


def test_infeasible_and_not_a_matrix():
    cost = np.array([[np.inf, np.inf], [1.0, 2.0]])
    with pytest.raises(ValueError, match="infeasible"):
        linear_sum_assignment(cost)
    with pytest.raises(ValueError, match="2-D"):
        linear_sum_assignment(np.ones(3))
