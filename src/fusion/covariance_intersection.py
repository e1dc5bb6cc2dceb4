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

which decreases in w: w = 1 where g(1) >= 0 (the estimate would only loosen the track; no
update), else found by bisection on [W_MIN, 1] to machine precision, vectorised over the
tracks. Why not a grid (its resolution limits the optimum) or the improved fast CI of
Franken & Hupper (a closed-form approximation for full-rank pairs): the exact optimum costs
K x m eigenvalues and 52 halvings of (K, m) arrays. For a partial observation (m < n) the
(n - m) log w term keeps w > 0: scaling the track's information down loses the unobserved
entries too, so the track keeps its weight unless the estimate is markedly better
(sum_i (lambda_i - 1) > n - m at w = 1).
"""

from __future__ import annotations

import numpy as np

W_MIN = 1e-6  # smallest weight of the track (full observations: w -> 0 takes the estimate)
_HALVINGS = 52  # bisection steps: the bracket [W_MIN, 1] shrinks to 2^-52


def _valid_pairs(p_obs: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(K,) True where H P H^T (K, m, m) and R (K, m, m) are finite and positive definite."""
    ok = np.isfinite(p_obs).all(axis=(1, 2)) & np.isfinite(r).all(axis=(1, 2))
    for a in (p_obs, r):
        sym = 0.5 * (a[ok] + np.swapaxes(a[ok], -1, -2))
        eig = np.linalg.eigvalsh(sym)  # ascending, (K', m)
        ok[np.flatnonzero(ok)] = eig[:, 0] > 1e-12 * np.abs(eig[:, -1])
    return ok


def generalized_eigenvalues(s: np.ndarray, r: np.ndarray) -> np.ndarray:
    """lambda (K, m): eigenvalues of R^-1 S for symmetric positive definite S, R (K, m, m).

    With R = L L^T: R^-1 S is similar to the symmetric L^-1 S L^-T, whose eigenvalues are real.
    """
    chol = np.linalg.cholesky(r)
    half = np.linalg.solve(chol, s)  # L^-1 S
    return np.linalg.eigvalsh(np.linalg.solve(chol, np.swapaxes(half, -1, -2)))  # L^-1 S L^-T


def ci_weights(p: np.ndarray, r: np.ndarray, first: int = 0) -> np.ndarray:
    """Weights w (K,) of the tracks that minimise det P+ (module docstring).

    p (K, n, n): track covariances; r (K, m, m): covariances of estimates of the state entries
    first .. first + m - 1. Pairs that are not finite and positive definite get w = 1 (the
    estimate is not used).
    """
    k, n, m = len(p), p.shape[-1], r.shape[-1]
    sel = slice(first, first + m)
    p_obs = p[:, sel, sel]
    w = np.ones(k)
    ok = _valid_pairs(p_obs, r)
    if not ok.any():
        return w
    lam = generalized_eigenvalues(0.5 * (p_obs[ok] + np.swapaxes(p_obs[ok], -1, -2)), r[ok])

    def slope(wt: np.ndarray) -> np.ndarray:  # g(w) = (n - m) / w + sum (1 - lambda) / (w (1 - lambda) + lambda)
        wt = wt[:, None]
        return (n - m) / wt[:, 0] + ((1 - lam) / (wt * (1 - lam) + lam)).sum(axis=1)

    lo, hi = np.full(len(lam), W_MIN), np.ones(len(lam))
    for _ in range(_HALVINGS):
        mid = 0.5 * (lo + hi)
        rising = slope(mid) > 0  # the optimum lies above mid
        lo, hi = np.where(rising, mid, lo), np.where(rising, hi, mid)
    sub = 0.5 * (lo + hi)
    sub[slope(np.ones(len(lam))) >= 0] = 1.0
    sub[slope(np.full(len(lam), W_MIN)) <= 0] = W_MIN
    w[ok] = sub
    return w


def ci_update(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray, w: np.ndarray,
              first: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """CI of K tracks x (K, n), P (K, n, n) with estimates z (K, m), R (K, m, m) of the state
    entries first .. first + m - 1, weights w (K,): the Kalman update with P / w and
    R / (1 - w) (module docstring). Rows with w = 1 are returned unchanged. New arrays."""
    x, p = x.copy(), p.copy()
    use = w < 1.0
    if not use.any():
        return x, p
    wu = w[use][:, None, None]
    pw, rw = p[use] / wu, r[use] / (1.0 - wu)
    sel = slice(first, first + r.shape[-1])
    s = pw[:, sel, sel] + rw  # S = H P H^T / w + R / (1 - w)
    gain = np.swapaxes(np.linalg.solve(s, np.swapaxes(pw[:, :, sel], -1, -2)), -1, -2)  # K = (P / w) H^T S^-1
    x[use] = x[use] + (gain @ (z[use] - x[use, sel])[:, :, None])[:, :, 0]
    # Joseph form with A = (I - K H) P / w: P+ = A + (K R' - A H^T) K^T (as kalman.update)
    a = pw - gain @ pw[:, sel, :]
    p[use] = a + (gain @ rw - a[:, :, sel]) @ np.swapaxes(gain, -1, -2)
    return x, p


def covariance_intersection(x1: np.ndarray, p1: np.ndarray, x2: np.ndarray, p2: np.ndarray,
                            w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Information form of CI for full estimates x1, x2 (K, n), P1, P2 (K, n, n), w (K,) in (0, 1):
    P = (w P1^-1 + (1 - w) P2^-1)^-1, x = P (w P1^-1 x1 + (1 - w) P2^-1 x2) (the reference)."""
    i1, i2 = np.linalg.inv(p1), np.linalg.inv(p2)
    wt = w[:, None, None]
    p = np.linalg.inv(wt * i1 + (1 - wt) * i2)
    info = wt * i1 @ x1[:, :, None] + (1 - wt) * i2 @ x2[:, :, None]
    return (p @ info)[:, :, 0], p
