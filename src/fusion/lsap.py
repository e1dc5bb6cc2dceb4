"""Linear sum assignment, compiled: the shortest augmenting path algorithm of Crouse (2016), the one
behind ``scipy.optimize.linear_sum_assignment``, with the same choices where costs tie, so the
same matching (tests/unit/test_lsap.py compares the two on random, tied, infinite and
rectangular costs).

Why not scipy's: importing ``scipy.optimize`` costs a service ~0.15-0.2 s of its start-up (the
package's ``__init__`` loads linalg, sparse, fft and the rest), most of scipy's time in a
process that needs nothing else of it; and the call's own overhead is paid thousands of times
per evaluated run.

The algorithm (D. F. Crouse, "On implementing 2D rectangular assignment algorithms", IEEE TAES
52(4), 2016, pp. 1685-1686): rows are added one at a time; for row ``start`` a Dijkstra search
over reduced costs c[i, j] - u[i] - v[j] >= 0 finds the cheapest alternating path to a free
column (the sink), the duals are updated so reduced costs stay >= 0 and the path's matched
edges tight, and the matching is flipped along the path. A wide problem (more rows than
columns) is solved transposed.
"""

from __future__ import annotations

import numpy as np

from .jit import B1, IN_F2, kernel

INFEASIBLE, INVALID = 1, 2


def linear_sum_assignment(cost: np.ndarray, maximize: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """rows (k,), cols (k,): a matching of min(n, m) pairs of least total cost (greatest with
    ``maximize``) of the (n, m) cost; rows ascending. ValueError for a NaN or -inf cost (+inf
    under ``maximize``) and when every complete matching uses an infinite cost, as scipy."""
    cost = np.asarray(cost, dtype=np.float64)
    if cost.ndim != 2:
        raise ValueError(f"expected a matrix (2-D array), got a {cost.ndim}-D array")
    status, rows, cols = _solve(cost, maximize)
    if status == INVALID:
        raise ValueError("matrix contains invalid numeric entries")
    if status == INFEASIBLE:
        raise ValueError("cost matrix is infeasible")
    return rows, cols


@kernel(IN_F2, B1)
def _solve(cost: np.ndarray, maximize: bool) -> tuple[int, np.ndarray, np.ndarray]:
    """(status, rows, cols): status 0, INFEASIBLE or INVALID (rows, cols then empty)."""
    n, m = cost.shape
    wide = m < n  # solved transposed: its rows are then the columns
    n_r, n_c = (m, n) if wide else (n, m)
    c = np.empty((n_r, n_c))
    for i in range(n_r):
        for j in range(n_c):
            x = cost[j, i] if wide else cost[i, j]
            c[i, j] = -x if maximize else x
            if c[i, j] != c[i, j] or c[i, j] == -np.inf:
                return INVALID, np.empty(0, np.int64), np.empty(0, np.int64)
    u, v, dist = np.zeros(n_r), np.zeros(n_c), np.empty(n_c)
    col_of, row_of, pred = np.full(n_r, -1), np.full(n_c, -1), np.full(n_c, -1)
    row_done, col_done, todo = np.empty(n_r, np.bool_), np.empty(n_c, np.bool_), np.empty(n_c, np.int64)
    for start in range(n_r):
        # Dijkstra from row `start`: dist[j] = cheapest reduced-cost path to column j so far
        row_done[:], col_done[:], dist[:] = False, False, np.inf
        n_todo = n_c
        for k in range(n_c):
            todo[k] = n_c - 1 - k  # columns in reverse: a constant cost gives the identity matching
        i, reach, sink = start, 0.0, -1
        while sink < 0:
            row_done[i] = True
            best, lowest = -1, np.inf
            for k in range(n_todo):
                j = todo[k]
                d = reach + c[i, j] - u[i] - v[j]
                if d < dist[j]:
                    pred[j], dist[j] = i, d
                # on a tie, a free column (it ends the path) wins
                if dist[j] < lowest or (dist[j] == lowest and row_of[j] < 0):
                    best, lowest = k, dist[j]
            reach = lowest
            if reach == np.inf:
                return INFEASIBLE, np.empty(0, np.int64), np.empty(0, np.int64)
            j = todo[best]
            if row_of[j] < 0:
                sink = j
            else:
                i = row_of[j]
            col_done[j] = True
            n_todo -= 1
            todo[best] = todo[n_todo]
        # duals: u[i] + v[j] <= c[i, j] everywhere, with equality on matched pairs and the path
        u[start] += reach
        for i in range(n_r):
            if row_done[i] and i != start:
                u[i] += reach - dist[col_of[i]]
        for j in range(n_c):
            if col_done[j]:
                v[j] -= reach - dist[j]
        # flip the matching along the path, back from the sink to `start`
        j = sink
        while True:
            i = pred[j]
            row_of[j] = i
            j, col_of[i] = col_of[i], j
            if i == start:
                break
    if not wide:
        return 0, np.arange(n_r), col_of
    order = np.argsort(col_of)  # by the original row
    return 0, col_of[order], order
