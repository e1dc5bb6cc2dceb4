"""Global nearest-neighbour association with gating (scipy's Hungarian solver)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

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
