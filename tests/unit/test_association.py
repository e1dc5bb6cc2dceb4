"""association.assign_sparse (per connected component of the gated graph) against scipy's
linear_sum_assignment on the whole gated cost (forbidden pairs at a prohibitive cost)."""

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from v2i.fusion.association import assign_sparse, center_distance_cost

BIG = 1e12


def reference(a, b, cost, n_a, n_b):
    """scipy on the dense (n_a, n_b) gated cost: the largest matching of allowed pairs, then the cheapest."""
    dense = np.full((n_a, n_b), BIG)
    dense[a, b] = cost
    r, c = linear_sum_assignment(dense)
    ok = dense[r, c] < BIG
    return np.column_stack([r[ok], c[ok]])


def random_gated(rng, n_a, n_b, density, integer_costs):
    """K distinct allowed pairs of an (n_a, n_b) problem, shuffled, with costs (K,)."""
    allowed = rng.random((n_a, n_b)) < density
    a, b = np.nonzero(allowed)
    order = rng.permutation(len(a))
    a, b = a[order], b[order]
    cost = rng.integers(0, 3, len(a)).astype(float) if integer_costs else rng.uniform(0, 5, len(a))
    return a, b, cost


def check_matching(result, a, b, n_a, n_b):
    """One-to-one, allowed pairs only, unmatched = the complement."""
    m = result.matches
    allowed = set(zip(a.tolist(), b.tolist()))
    assert all((i, j) in allowed for i, j in m.tolist())
    assert len(set(m[:, 0].tolist())) == len(m) and len(set(m[:, 1].tolist())) == len(m)
    assert np.array_equal(np.sort(np.concatenate([m[:, 0], result.unmatched_a])), np.arange(n_a))
    assert np.array_equal(np.sort(np.concatenate([m[:, 1], result.unmatched_b])), np.arange(n_b))
    assert np.all(np.diff(m[:, 0]) > 0)  # sorted by a


@pytest.mark.parametrize("density", [0.01, 0.03, 0.1, 0.4])
def test_distinct_costs_give_scipy_s_matching(density):
    rng = np.random.default_rng(round(density * 100))
    singles = 0
    for _ in range(60):
        n_a, n_b = rng.integers(0, 40, 2)
        a, b, cost = random_gated(rng, n_a, n_b, density, integer_costs=False)
        got = assign_sparse(a, b, cost, n_a, n_b)
        check_matching(got, a, b, n_a, n_b)
        assert np.array_equal(got.matches, reference(a, b, cost, n_a, n_b))
        singles += int(np.sum((np.bincount(a, minlength=n_a)[a] == 1) & (np.bincount(b, minlength=n_b)[b] == 1)))
    assert singles > 0  # the single-pair shortcut was exercised


def test_ties_give_a_matching_of_the_same_size_and_cost():
    """Integer costs tie often: any optimum will do, with scipy's size and total cost."""
    rng = np.random.default_rng(11)
    for _ in range(200):
        n_a, n_b = rng.integers(1, 25, 2)
        a, b, cost = random_gated(rng, n_a, n_b, rng.uniform(0.02, 0.5), integer_costs=True)
        got = assign_sparse(a, b, cost, n_a, n_b)
        check_matching(got, a, b, n_a, n_b)
        ref = reference(a, b, cost, n_a, n_b)
        lookup = {(i, j): c for i, j, c in zip(a.tolist(), b.tolist(), cost.tolist())}
        assert len(got.matches) == len(ref)
        assert sum(lookup[p] for p in map(tuple, got.matches.tolist())) == sum(lookup[p] for p in map(tuple, ref.tolist()))


def test_largest_matching_before_cheapest_across_a_chain():
    """a0-b0 is cheapest, but taking it leaves a1 without a partner: both pairs of the chain win."""
    a, b, cost = np.array([0, 0, 1]), np.array([0, 1, 0]), np.array([0.1, 4.0, 4.0])
    got = assign_sparse(a, b, cost, 2, 2)
    assert got.matches.tolist() == [[0, 1], [1, 0]]
    assert np.array_equal(got.matches, reference(a, b, cost, 2, 2))


def test_empty_problems_and_isolated_nodes():
    none = np.zeros(0, np.int64)
    for n_a, n_b in ((0, 0), (0, 5), (4, 0), (3, 3)):
        got = assign_sparse(none, none, np.zeros(0), n_a, n_b)
        assert got.matches.shape == (0, 2)
        assert got.unmatched_a.tolist() == list(range(n_a)) and got.unmatched_b.tolist() == list(range(n_b))
    # one pair in a 5 x 6 problem: everything else unmatched
    got = assign_sparse(np.array([3]), np.array([4]), np.array([2.0]), 5, 6)
    assert got.matches.tolist() == [[3, 4]]
    assert got.unmatched_a.tolist() == [0, 1, 2, 4] and got.unmatched_b.tolist() == [0, 1, 2, 3, 5]


@pytest.mark.parametrize("dim", [2, 3])
def test_center_distance_cost_is_scipys_cdist_bit_for_bit(dim):
    """The scorers use it in place of cdist (scipy.spatial costs ~0.15 s to import)."""
    rng = np.random.default_rng(dim)
    for n, m in [(1, 1), (7, 3), (40, 55)]:
        a, b = rng.normal(scale=80.0, size=(n, dim)), rng.normal(scale=80.0, size=(m, dim))
        np.testing.assert_array_equal(center_distance_cost(a, b), cdist(a, b))
