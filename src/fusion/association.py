"""Global nearest-neighbour association with gating (scipy's Hungarian solver).

``assign`` takes a dense cost and a gate; ``assign_sparse`` takes only the K pairs that passed
the gate (the tracker's path): the gated bipartite graph splits into connected components, and
a minimum-cost matching of the largest size is one per component. Most components of a
tracker's gated graph are a single pair (its track and its detection in no other pair): that
pair is matched as it is, without the solver; the remaining components go to one
``linear_sum_assignment`` over their own rows and columns, a block-diagonal problem whose
blocks are never matched across (pairs outside the gate cost ``_BIG``, so a matching of the
largest size is the cheapest; tests/unit/test_association.py checks the result against the
solver on the whole gated cost).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from .fastnp import all_true, filled, true_index

_BIG = 1e12


@dataclass(frozen=True)
class Assignment:
    """matches (K, 2) rows of (a index, b index); unmatched_a (.,), unmatched_b (.,)."""

    matches: np.ndarray
    unmatched_a: np.ndarray
    unmatched_b: np.ndarray


def assign(cost: np.ndarray, gate: float) -> Assignment:
    """Minimum-cost one-to-one matching of rows (a) to columns (b) among pairs with cost <= gate.

    Gated-out pairs (cost > gate, inf or NaN) are never matched.
    """
    cost = np.asarray(cost, dtype=float)
    n, m = cost.shape
    allowed = np.isfinite(cost) & (cost <= gate)
    if not allowed.any():
        return Assignment(np.zeros((0, 2), dtype=int), np.arange(n), np.arange(m))
    rows, cols = linear_sum_assignment(np.where(allowed, cost, _BIG))
    keep = allowed[rows, cols]
    matches = np.column_stack([rows[keep], cols[keep]]).astype(int)
    return Assignment(
        matches,
        np.setdiff1d(np.arange(n), matches[:, 0]),
        np.setdiff1d(np.arange(m), matches[:, 1]),
    )


def center_distance_cost(a_xy: np.ndarray, b_xy: np.ndarray, a_cls=None, b_cls=None) -> np.ndarray:
    """Euclidean centre distance (N, M) in metres; inf across different classes when given."""
    cost = np.linalg.norm(np.asarray(a_xy)[:, None, :] - np.asarray(b_xy)[None, :, :], axis=-1)
    if a_cls is not None and b_cls is not None:
        cost = np.where(np.asarray(a_cls)[:, None] == np.asarray(b_cls)[None, :], cost, np.inf)
    return cost


def assign_sparse(a: np.ndarray, b: np.ndarray, cost: np.ndarray, n_a: int, n_b: int) -> Assignment:
    """Largest one-to-one matching of minimum cost among K allowed pairs (a[k], b[k]) with cost
    (K,), a in [0, n_a), b in [0, n_b); pairs appear at most once. Matches sorted by a.

    A pair whose a and b are in no other pair is a component of its own and is matched; the
    other pairs are solved together over their distinct rows and columns (module docstring).
    The matches are collected in ``mate`` (n_a,), the b matched to each a (-1: none), which
    sorts them by a without a sort.
    """
    a, b = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    # every pair counts once for its a and once for its b: the counts sum to 2 exactly when both are 1
    single = (np.bincount(a, minlength=n_a).take(a) + np.bincount(b, minlength=n_b).take(b)) == 2
    mate = np.empty(n_a, np.int64)
    mate.fill(-1)
    if all_true(single):
        mate[a] = b
    else:
        one, rest = true_index(single), true_index(~single)
        mate[a.take(one)] = b.take(one)
        rows, ri = _compact(a.take(rest), n_a)
        cols, ci = _compact(b.take(rest), n_b)
        sub = np.empty((len(rows), len(cols)))
        sub.fill(_BIG)
        sub[ri, ci] = cost.take(rest)
        r, c = linear_sum_assignment(sub)
        ok = true_index(sub[r, c] < _BIG)
        mate[rows.take(r.take(ok))] = cols.take(c.take(ok))
    matched = mate >= 0
    ma = true_index(matched)
    matches = np.empty((len(ma), 2), np.int64)
    matches[:, 0] = ma
    matches[:, 1] = mb = mate.take(ma)
    free_b = filled(n_b, True, bool)
    free_b[mb] = False
    return Assignment(matches, true_index(~matched), true_index(free_b))


def _compact(index: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The distinct values of index (sorted) in [0, size) and the position of each entry among them."""
    present = np.zeros(size, bool)
    present[index] = True
    values = true_index(present)
    lookup = np.empty(size, np.int64)
    lookup[values] = np.arange(len(values))
    return values, lookup[index]
