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
g(W_MIN) <= 0, else the root in between, found by safeguarded Newton:
w <- w - g(w) / g'(w), a bisection step of the bracket [lo, hi] (g(lo) > 0 > g(hi))
wherever Newton would leave it. It stops when a Newton step is below ``W_TOL`` = 1e-12:
Newton converges quadratically, so the error after such a step is O(1e-24), below the
rounding of g itself; the weight is the 52-halving bisection's to ~1e-15 (both are exact to
rounding) at about 5 iterations instead of 52 (tests/unit/test_multi_source.py compares them).
Why not a grid (its resolution limits the optimum) or the improved fast CI of
Franken & Hupper (a closed-form approximation for full-rank pairs): the exact optimum costs
m eigenvalues and a few Newton steps per track. For a partial observation (m < n) the
(n - m) log w term keeps w > 0: scaling the track's information down loses the unobserved
entries too, so the track keeps its weight unless the estimate is markedly better
(sum_i (lambda_i - 1) > n - m at w = 1).

The tracker fuses a few estimates per list, so the cost is per call, not per pair: the weights
and the update run as compiled kernels (numba), one pair at a time, with a Cholesky factor and
the eigenvalues in closed form for m = 2 (position) and LAPACK's for m = 4 (position and velocity).
``covariance_intersection`` (the information form, numpy) is the reference they are tested against.
"""

from __future__ import annotations

import math

import numpy as np

from schemas.messages import UNKNOWN_VELOCITY_VAR  # per-axis velocity variance meaning "no velocity"

from .jit import B1, I64, IN_F1, IN_F2, IN_F3, IN_I1, OUT_F2, OUT_F3, helper, kernel

W_MIN = 1e-6  # smallest weight of the track (full observations: w -> 0 takes the estimate)
W_TOL = 1e-12  # Newton stops once a step is below this (module docstring)
_MAX_STEPS = 60  # safeguard: each step at least halves the bracket where Newton fails, 2^-60 < W_TOL
_PD_RATIO = 1e-12  # R^-1 H P H^T counts as positive definite when its smallest eigenvalue is above this of the largest


def ci_weights(p: np.ndarray, r: np.ndarray, first: int = 0) -> np.ndarray:
    """Weights w (K,) of the tracks that minimise det P+ (module docstring).

    p (K, n, n): track covariances; r (K, m, m): covariances of estimates of the state entries
    first .. first + m - 1. Pairs that are not finite and positive definite get w = 1 (the
    estimate is not used): R must have a Cholesky factor, and the eigenvalues of R^-1 H P H^T
    must be positive, the smallest above 1e-12 of the largest.
    """
    return _weights(np.asarray(p, dtype=float), np.asarray(r, dtype=float), first)


def ci_update(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray, w: np.ndarray,
              first: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """CI of K tracks x (K, n), P (K, n, n) with estimates z (K, m), R (K, m, m) of the state
    entries first .. first + m - 1, weights w (K,): the Kalman update with P / w and
    R / (1 - w) (module docstring). Rows with w = 1 are returned unchanged. New arrays."""
    x, p = np.array(x, dtype=float), np.array(p, dtype=float)
    ci_update_into(x, p, z, r, w, first)
    return x, p


def ci_update_into(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray, w: np.ndarray,
                   first: int = 0, rows: np.ndarray | None = None) -> None:
    """``ci_update`` written into x (K, n) and P (K, n, n) (float64); with ``rows`` (K,), into the rows
    rows[k] of larger x, P (a track table), pair k being (x[rows[k]], P[rows[k]]) with (z[k], R[k], w[k])."""
    rows = np.arange(len(z)) if rows is None else np.asarray(rows, dtype=np.int64)
    _update_rows(x, p, rows, np.asarray(z, dtype=float), np.asarray(r, dtype=float),
                 np.asarray(w, dtype=float), first)


def ci_fuse_rows(x: np.ndarray, p: np.ndarray, rows: np.ndarray, z: np.ndarray, r: np.ndarray) -> None:
    """CI of the tracks rows (K,) of a table x (N, n), P (N, n, n) with estimates z (K, m), R (K, m, m)
    of their first m state entries, in place: ``ci_weights`` of the K pairs, then ``ci_update_into``
    (the tracker's path, ``ci_fuse_objects``, takes z and R from an object list itself)."""
    rows = np.asarray(rows, dtype=np.int64)
    ci_update_into(x, p, z, r, ci_weights(p[rows], r), 0, rows)


# --- compiled kernels (numba; the equations of the module docstring, one pair at a time) ------------


@helper
def _inverse_cholesky(r: np.ndarray, out: np.ndarray) -> bool:
    """out (m, m) = L^-1 with r = L L^T (lower); False where r has no factor (not positive definite, NaN)."""
    m = r.shape[0]
    chol = np.zeros((m, m))
    for j in range(m):
        d = r[j, j]
        for k in range(j):
            d -= chol[j, k] * chol[j, k]
        if not d > 0.0:
            return False
        chol[j, j] = math.sqrt(d)
        for i in range(j + 1, m):
            s = r[i, j]
            for k in range(j):
                s -= chol[i, k] * chol[j, k]
            chol[i, j] = s / chol[j, j]
    for c in range(m):  # forward substitution L out = I (out lower triangular)
        for i in range(m):
            s = 1.0 if i == c else 0.0
            for k in range(c, i):
                s -= chol[i, k] * out[k, c]
            out[i, c] = s / chol[i, i] if i >= c else 0.0
    return True


@helper
def _generalised_eigenvalues(p: np.ndarray, inv_l: np.ndarray, first: int) -> np.ndarray:
    """Ascending eigenvalues (m,) of L^-1 sym(H P H^T) L^-T = those of R^-1 H P H^T (R = L L^T)."""
    m = inv_l.shape[0]
    a = np.zeros((m, m))  # L^-1 sym(P_obs) L^-T
    for i in range(m):
        for j in range(m):
            s = 0.0
            for k in range(m):
                pk = 0.0
                for q in range(m):
                    pk += 0.5 * (p[first + k, first + q] + p[first + q, first + k]) * inv_l[j, q]
                s += inv_l[i, k] * pk
            a[i, j] = s
    if m == 2:  # closed form: mean -+ sqrt(half difference^2 + off-diagonal^2)
        mid, half = 0.5 * (a[0, 0] + a[1, 1]), math.hypot(0.5 * (a[0, 0] - a[1, 1]), a[1, 0])
        out = np.empty(2)
        out[0], out[1] = mid - half, mid + half
        return out
    return np.linalg.eigvalsh(a)


@helper
def _weight(p: np.ndarray, r: np.ndarray, first: int) -> float:
    """w of one track P (n, n) and estimate R (m, m) of entries first .. first + m - 1 (``ci_weights``)."""
    n, m = p.shape[0], r.shape[0]
    for i in range(m):
        for j in range(m):
            if not (math.isfinite(p[first + i, first + j]) and math.isfinite(r[i, j])):
                return 1.0
    inv_l = np.empty((m, m))
    if not _inverse_cholesky(r, inv_l):
        return 1.0
    lam = _generalised_eigenvalues(p, inv_l, first)
    if not lam[0] > _PD_RATIO * abs(lam[m - 1]):  # H P H^T not positive definite (or NaN)
        return 1.0
    return _det_minimising_weight(lam, n - m)


@helper
def _g(w: float, lam: np.ndarray, free: int) -> tuple[float, float]:
    """g(w) = free / w + sum a / (a w + lambda), a = 1 - lambda, and g'(w) (module docstring)."""
    g, dg = 0.0, 0.0
    for lam_i in lam:
        a = 1.0 - lam_i
        q = a / (a * w + lam_i)
        g += q
        dg -= q * q
    if free:
        g += free / w
        dg -= free / (w * w)
    return g, dg


@helper
def _det_minimising_weight(lam: np.ndarray, free: int) -> float:
    """w in [W_MIN, 1] maximising free log w + sum_i log(w (1 - lambda_i) + lambda_i), eigenvalues lam (m,) > 0,
    free = n - m unobserved state entries: a bound, or the root of the decreasing g by safeguarded Newton."""
    if _g(W_MIN, lam, free)[0] <= 0:
        return W_MIN
    if _g(1.0, lam, free)[0] >= 0:  # the estimate would only loosen the track
        return 1.0
    lo, hi, w = W_MIN, 1.0, 0.5  # g(lo) > 0 > g(hi)
    for _ in range(_MAX_STEPS):
        g, dg = _g(w, lam, free)
        if g > 0:  # the root lies above w
            lo = w
        else:
            hi = w
        nxt = w - g / dg
        if not (nxt >= lo and nxt <= hi):  # bisect where Newton leaves the bracket (or is NaN)
            nxt = 0.5 * (lo + hi)
        step = abs(nxt - w)
        w = nxt
        if step <= W_TOL:
            break
    return w


@helper
def _update_pair(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray, w: float, first: int) -> None:
    """CI of one track x (n,), P (n, n) with z (m,), R (m, m) and weight w < 1, in place (Joseph form):
    S = H P H^T / w + R / (1 - w), K = (P / w) H^T S^-1, x+ = x + K (z - H x),
    A = (I - K H) P / w, P+ = A + (K R / (1 - w) - A H^T) K^T (as kalman.update)."""
    n, m = p.shape[0], r.shape[0]
    pw, rw = p / w, r / (1.0 - w)
    s = np.empty((m, m))
    for i in range(m):
        for j in range(m):
            s[i, j] = pw[first + i, first + j] + rw[i, j]
    gain = np.linalg.solve(s, np.ascontiguousarray(pw[first:first + m, :])).T  # (n, m); S symmetric
    y = z - x[first:first + m]  # innovation, before x changes
    for i in range(n):
        dx = 0.0
        for j in range(m):
            dx += gain[i, j] * y[j]
        x[i] += dx
    a = pw.copy()  # A = P / w - K (H P / w)
    for i in range(n):
        for j in range(n):
            for k in range(m):
                a[i, j] -= gain[i, k] * pw[first + k, j]
    b = np.empty((n, m))  # K R' - A H^T
    for i in range(n):
        for j in range(m):
            s_ij = -a[i, first + j]
            for k in range(m):
                s_ij += gain[i, k] * rw[k, j]
            b[i, j] = s_ij
    for i in range(n):
        for j in range(n):
            s_ij = a[i, j]
            for k in range(m):
                s_ij += b[i, k] * gain[j, k]
            p[i, j] = s_ij


@helper
def _update_each(x: np.ndarray, p: np.ndarray, rows: np.ndarray, z: np.ndarray, r: np.ndarray, w: np.ndarray,
                 first: int) -> None:
    """``_update_pair`` of rows[k] of x, P with z[k], R[k], w[k], wherever w[k] < 1."""
    for k in range(rows.shape[0]):
        if w[k] < 1.0:
            _update_pair(x[rows[k]], p[rows[k]], z[k], r[k], w[k], first)


@kernel(IN_F3, IN_F3, I64)
def _weights(p: np.ndarray, r: np.ndarray, first: int) -> np.ndarray:
    w = np.empty(p.shape[0])
    for k in range(p.shape[0]):
        w[k] = _weight(p[k], r[k], first)
    return w


@kernel(OUT_F2, OUT_F3, IN_I1, IN_F2, IN_F3, IN_F1, I64)
def _update_rows(x: np.ndarray, p: np.ndarray, rows: np.ndarray, z: np.ndarray, r: np.ndarray, w: np.ndarray,
                 first: int) -> None:
    _update_each(x, p, rows, z, r, w, first)


@kernel(OUT_F2, OUT_F3, IN_I1, IN_F2, IN_F3, IN_F2, IN_F3, IN_I1, B1)
def ci_fuse_objects(x: np.ndarray, p: np.ndarray, rows: np.ndarray, xy: np.ndarray, cov_xy: np.ndarray,
                    vxy: np.ndarray, cov_vxy: np.ndarray, cols: np.ndarray, velocity: bool) -> None:
    """CI of the tracks rows (K,) of a table x (N, n), P (N, n, n) with the objects cols (K,) of a list (xy (M, 2),
    cov_xy, vxy, cov_vxy (M, 2, 2)), in place: z = xy, R = cov_xy, or with ``velocity`` where the object measured
    one (trace cov_vxy < UNKNOWN_VELOCITY_VAR, ``ObjectArray.velocity_known``) z = [xy, vxy],
    R = blockdiag(cov_xy, cov_vxy); ``ci_fuse_rows`` of each pair (every weight from the prior covariances)."""
    n_pairs = rows.shape[0]
    w, dim = np.empty(n_pairs), np.empty(n_pairs, np.int64)
    z, r = np.zeros((n_pairs, 4)), np.zeros((n_pairs, 4, 4))  # pair k: z[k, :m], R[k, :m, :m], m = dim[k]
    for k in range(n_pairs):
        j = cols[k]
        m = 4 if velocity and cov_vxy[j, 0, 0] + cov_vxy[j, 1, 1] < UNKNOWN_VELOCITY_VAR else 2
        for a in range(2):
            z[k, a], z[k, 2 + a] = xy[j, a], vxy[j, a]
            for b in range(2):
                r[k, a, b], r[k, 2 + a, 2 + b] = cov_xy[j, a, b], cov_vxy[j, a, b]
        dim[k] = m
        w[k] = _weight(p[rows[k]], r[k, :m, :m], 0)
    for k in range(n_pairs):
        if w[k] < 1.0:
            m = dim[k]
            _update_pair(x[rows[k]], p[rows[k]], z[k, :m], r[k, :m, :m], w[k], 0)


def covariance_intersection(x1: np.ndarray, p1: np.ndarray, x2: np.ndarray, p2: np.ndarray,
                            w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Information form of CI for full estimates x1, x2 (K, n), P1, P2 (K, n, n), w (K,) in (0, 1):
    P = (w P1^-1 + (1 - w) P2^-1)^-1, x = P (w P1^-1 x1 + (1 - w) P2^-1 x2) (the reference)."""
    i1, i2 = np.linalg.inv(p1), np.linalg.inv(p2)
    wt = w[:, None, None]
    p = np.linalg.inv(wt * i1 + (1 - wt) * i2)
    info = wt * i1 @ x1[:, :, None] + (1 - wt) * i2 @ x2[:, :, None]
    return (p @ info)[:, :, 0], p
