"""Covariance intersection (CI) of track states with estimates whose errors are correlated
in an unknown way (Julier & Uhlmann), batched over K tracks.

Two estimates (x1, P1), (x2, P2) of one state with unknown cross-covariance are fused by

    P^-1 = w P1^-1 + (1 - w) P2^-1,   x = P (w P1^-1 x1 + (1 - w) P2^-1 x2),   w in [0, 1],

which is consistent (P bounds the true error covariance) for every cross-covariance. A
track x (n,) observed partially by an estimate z = H x (m entries, R) is the same fusion
with P2^-1 = H^T R^-1 H, and equals a Kalman update with the inflated covariances P / w and
R / (1 - w):

    S = H P H^T / w + R / (1 - w),  K = (P / w) H^T S^-1,  x+ = x + K (z - H x),
    P+ = (I - K H) (P / w) (I - K H)^T + K (R / (1 - w)) K^T        (Joseph form)

The weight minimises det P+ (Julier & Uhlmann's criterion; the determinant, unlike the
trace, does not depend on the units, and the state mixes m and m/s). With lambda_i the m
generalised eigenvalues of (H P H^T, R) (the eigenvalues of R^-1 H P H^T) the matrix
determinant lemma gives

    log det P+^-1(w) = const + (n - m) log w + sum_i log(w (1 - lambda_i) + lambda_i),

concave in w, so the minimiser is the root of its derivative

    g(w) = (n - m) / w + sum_i (1 - lambda_i) / (w (1 - lambda_i) + lambda_i),

which decreases in w (g'(w) = -(n - m) / w^2 - sum_i (1 - lambda_i)^2 / (w (1 - lambda_i) + lambda_i)^2):
w = 1 where g(1) >= 0 (the estimate would only loosen the track; no update), W_MIN where
g(W_MIN) <= 0, else the root in between, found by safeguarded Newton vectorised over the
tracks: w <- w - g(w) / g'(w), a bisection step of the bracket [lo, hi] (g(lo) > 0 > g(hi))
wherever Newton would leave it. It stops when every Newton step is below ``W_TOL`` = 1e-12:
Newton converges quadratically, so the error after such a step is O(1e-24), below the
rounding of g itself; the weight is the 52-halving bisection's to ~1e-15 (both are exact to
rounding) at about 5 iterations instead of 52 (tests/unit/test_multi_source.py compares them).
Why not a grid (its resolution limits the optimum) or the improved fast CI of
Franken & Hupper (a closed-form approximation for full-rank pairs): the exact optimum costs
K x m eigenvalues and a few Newton steps on (K, m) arrays. For a partial observation (m < n) the
(n - m) log w term keeps w > 0: scaling the track's information down loses the unobserved
entries too, so the track keeps its weight unless the estimate is markedly better
(sum_i (lambda_i - 1) > n - m at w = 1).
"""

from __future__ import annotations

import numpy as np

from .fastnp import all_true, any_true, eigvalsh_or_nan, filled, inverse_cholesky_or_nan, true_index

W_MIN = 1e-6  # smallest weight of the track (full observations: w -> 0 takes the estimate)
W_TOL = 1e-12  # Newton stops once every step is below this (module docstring)
_MAX_STEPS = 60  # safeguard: each step at least halves the bracket where Newton fails, 2^-60 < W_TOL


def det_minimising_weight(lam: np.ndarray, free: int) -> np.ndarray:
    """w (K,) in [W_MIN, 1] maximising free log w + sum_i log(w (1 - lambda_i) + lambda_i) for
    generalised eigenvalues lam (K, m) > 0 and free = n - m unobserved state entries (module docstring)."""
    a = 1.0 - lam  # g(w) = free / w + sum a / (a w + lambda)
    # (np.add.reduce: the same sums as .sum without its Python-level wrapper)
    g_one = free + np.add.reduce(a, axis=1)  # g(1): a + lambda = 1
    g_min = free / W_MIN + np.add.reduce(a / (a * W_MIN + lam), axis=1)
    w = np.where(g_min <= 0, W_MIN, 1.0)  # the bounds: at W_MIN where g(W_MIN) <= 0, else at 1 where g(1) >= 0
    inner = (g_one < 0) & (g_min > 0)  # the root lies strictly inside (W_MIN, 1)
    if any_true(inner):
        w[inner] = _newton_root(a[inner], lam[inner], free)
    return w


_SCALAR_ROWS = 3  # up to this many rows the Newton iteration runs on Python floats (_newton_root_scalar)


def _newton_root(a: np.ndarray, lam: np.ndarray, free: int) -> np.ndarray:
    """Root (K,) in (W_MIN, 1) of the decreasing g(w) = free / w + sum a / (a w + lam), a, lam (K, m),
    g(W_MIN) > 0 > g(1): safeguarded Newton (module docstring)."""
    if len(a) <= _SCALAR_ROWS:
        try:
            return _newton_root_scalar(a.tolist(), lam.tolist(), free)
        except ZeroDivisionError:  # numpy would carry an inf or nan on; let it
            pass
    return _newton_root_batched(a, lam, free)


def _newton_root_scalar(a: list[list[float]], lam: list[list[float]], free: int) -> np.ndarray:
    """``_newton_root_batched`` on a few rows in Python floats: the same operations in the same order
    (sums from the first term, every row stepped until all are done), so the same weights, without
    numpy's per-call cost (a single row took ~50 us in numpy, 4-5 steps of ~20 array operations)."""
    k = len(a)
    lo, hi, w = [W_MIN] * k, [1.0] * k, [0.5] * k
    for _ in range(_MAX_STEPS):
        done = True
        for i in range(k):
            wi, g, s2 = w[i], 0.0, 0.0
            for j, (aj, lj) in enumerate(zip(a[i], lam[i])):
                q = aj / (aj * wi + lj)
                g, s2 = (q, q * q) if j == 0 else (g + q, s2 + q * q)
            if free:
                g, dg = free / wi + g, -free / (wi * wi) - s2
            else:
                dg = -s2
            if g > 0:  # the root lies above w
                lo[i] = wi
            else:
                hi[i] = wi
            nxt = wi - g / dg
            if not (nxt >= lo[i] and nxt <= hi[i]):  # bisect where Newton leaves the bracket (or is nan)
                nxt = 0.5 * (lo[i] + hi[i])
            done = done and abs(nxt - wi) <= W_TOL
            w[i] = nxt
        if done:
            break
    return np.array(w)


def _newton_root_batched(a: np.ndarray, lam: np.ndarray, free: int) -> np.ndarray:
    """``_newton_root`` vectorised over the rows."""
    lo, hi = np.full(len(a), W_MIN), np.ones(len(a))
    w = np.full(len(a), 0.5)
    for _ in range(_MAX_STEPS):
        q = a / (a * w[:, None] + lam)
        if free:
            g = free / w + q.sum(axis=1)
            dg = -free / (w * w) - (q * q).sum(axis=1)
        else:  # full observation: the same numbers without the zero terms (0 / w + s == s, -0 - s == -s)
            g = q.sum(axis=1)
            dg = -(q * q).sum(axis=1)
        above = g > 0  # the root lies above w
        lo, hi = np.where(above, w, lo), np.where(above, hi, w)
        nxt = w - g / dg  # dg < 0: g(1) < 0 < g(W_MIN) leaves some a != 0
        nxt = np.where((nxt >= lo) & (nxt <= hi), nxt, 0.5 * (lo + hi))  # bisect where Newton leaves the bracket
        done = np.abs(nxt - w) <= W_TOL
        w = nxt
        if done.all():
            break
    return w


def ci_weights(p: np.ndarray, r: np.ndarray, first: int = 0) -> np.ndarray:
    """Weights w (K,) of the tracks that minimise det P+ (module docstring).

    p (K, n, n): track covariances; r (K, m, m): covariances of estimates of the state entries
    first .. first + m - 1. Pairs that are not finite and positive definite get w = 1 (the
    estimate is not used): R must have a Cholesky factor, and the eigenvalues of R^-1 H P H^T
    must be positive, the smallest above 1e-12 of the largest.
    """
    k, n, m = len(p), p.shape[-1], r.shape[-1]
    sel = slice(first, first + m)
    p_obs = p[:, sel, sel]
    if np.isfinite(np.add.reduce(p_obs, axis=None) + np.add.reduce(r, axis=None)):  # all finite (a sum is finite only if each term is)
        rows = None
    else:
        rows = np.flatnonzero(np.isfinite(p_obs).all(axis=(1, 2)) & np.isfinite(r).all(axis=(1, 2)))
        p_obs, r = p_obs[rows], r[rows]
    inv_l = inverse_cholesky_or_nan(r)  # L^-1, R = L L^T; NaN where R has no factor (positive definite to rounding)
    factored = ~np.isnan(inv_l[:, 0, 0])
    if not all_true(factored):
        rows = np.flatnonzero(factored) if rows is None else rows[factored]
        p_obs, inv_l = p_obs[factored], inv_l[factored]
    w = filled(k, 1.0)
    if not len(p_obs):
        return w
    # (.transpose(0, 2, 1) rather than np.swapaxes: the method skips a Python-level wrapper)
    lam = eigvalsh_or_nan(inv_l @ (0.5 * (p_obs + p_obs.transpose(0, 2, 1))) @ inv_l.transpose(0, 2, 1))
    # H P H^T positive definite: R^-1 S has positive eigenvalues, none below 1e-12 of the largest (NaN: no)
    pd = lam[:, 0] > 1e-12 * np.abs(lam[:, -1])
    if rows is None and all_true(pd):
        return det_minimising_weight(lam, n - m)
    rows = np.arange(k) if rows is None else rows
    w[rows[pd]] = det_minimising_weight(lam[pd], n - m)
    return w


def ci_update(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray, w: np.ndarray,
              first: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """CI of K tracks x (K, n), P (K, n, n) with estimates z (K, m), R (K, m, m) of the state
    entries first .. first + m - 1, weights w (K,): the Kalman update with P / w and
    R / (1 - w) (module docstring). Rows with w = 1 are returned unchanged. New arrays."""
    x, p = x.copy(), p.copy()
    ci_update_into(x, p, z, r, w, first)
    return x, p


def ci_update_into(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray, w: np.ndarray,
                   first: int = 0, rows: np.ndarray | None = None) -> None:
    """``ci_update`` written into x (K, n) and P (K, n, n); with ``rows`` (K,), into the rows rows[k]
    of larger x, P (a track table), pair k being (x[rows[k]], P[rows[k]]) with (z[k], R[k], w[k])."""
    use = w < 1.0
    every = all_true(use)
    if not every and not any_true(use):
        return
    if every:
        zu, ru, wu, target = z, r, w[:, None, None], rows
    else:
        use = true_index(use)  # (row gathers by .take: cheaper than boolean indexing on small batches)
        zu, ru, wu = z.take(use, axis=0), r.take(use, axis=0), w[use][:, None, None]
        target = use if rows is None else rows.take(use)
    if target is None:
        xu, pu = x, p
    else:
        xu, pu = x.take(target, axis=0), p.take(target, axis=0)
    pw, rw = pu / wu, ru / (1.0 - wu)
    sel = slice(first, first + r.shape[-1])
    s = pw[:, sel, sel] + rw  # S = H P H^T / w + R / (1 - w)
    gain = np.linalg.solve(s, pw[:, :, sel].transpose(0, 2, 1)).transpose(0, 2, 1)  # K = (P / w) H^T S^-1
    x_new = xu + (gain @ (zu - xu[:, sel])[:, :, None])[:, :, 0]
    # Joseph form with A = (I - K H) P / w: P+ = A + (K R' - A H^T) K^T (as kalman.update)
    a = pw - gain @ pw[:, sel, :]
    p_new = a + (gain @ rw - a[:, :, sel]) @ gain.transpose(0, 2, 1)
    if target is None:
        x[...], p[...] = x_new, p_new
    else:
        x[target], p[target] = x_new, p_new


def covariance_intersection(x1: np.ndarray, p1: np.ndarray, x2: np.ndarray, p2: np.ndarray,
                            w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Information form of CI for full estimates x1, x2 (K, n), P1, P2 (K, n, n), w (K,) in (0, 1):
    P = (w P1^-1 + (1 - w) P2^-1)^-1, x = P (w P1^-1 x1 + (1 - w) P2^-1 x2) (the reference)."""
    i1, i2 = np.linalg.inv(p1), np.linalg.inv(p2)
    wt = w[:, None, None]
    p = np.linalg.inv(wt * i1 + (1 - wt) * i2)
    info = wt * i1 @ x1[:, :, None] + (1 - wt) * i2 @ x2[:, :, None]
    return (p @ info)[:, :, 0], p
