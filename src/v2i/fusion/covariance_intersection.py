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

The tracker fuses a few estimates per list, so the cost is per call, not per pair: its CI of an
object list, ``ci_fuse_objects``, is one compiled kernel (numba), one pair at a time, with a
Cholesky factor, the eigenvalues in closed form for m = 2 (position) and LAPACK's for m = 4
(position and velocity), and S^-1 from S's Cholesky factor (numba's ``np.linalg.solve`` alone
took ~5 s of the kernel's compile). Its plain reference is ``ci_fuse_objects_reference``: the
batched numpy ``ci_weights`` and ``ci_update_into`` (the cooperative tracker of
``benchmarks/cycle_compute.py`` and the tests use those), equal to rounding
(tests/unit/test_tracker_rules.py). On the calls recorded in a connected-intersection run the
kernel takes 12 us per call against the reference's 176 us (2074 calls: 25 ms against 365 ms
of a ~2.4 s run), in the cycle benchmark 17 us against 270 us (~4 calls per cycle).
``covariance_intersection`` (the information form) is the reference of the update itself.
"""

from __future__ import annotations

import math

import numpy as np

from schemas.messages import UNKNOWN_VELOCITY_VAR  # per-axis velocity variance meaning "no velocity"

from v2i.core.jit import B1, IN_F2, IN_F3, IN_I1, OUT_F2, OUT_F3, helper, kernel

W_MIN = 1e-6  # smallest weight of the track (full observations: w -> 0 takes the estimate)
W_TOL = 1e-12  # Newton stops once a step is below this (module docstring)
_MAX_STEPS = 60  # safeguard: each step at least halves the bracket where Newton fails, 2^-60 < W_TOL
_PD_RATIO = 1e-12  # R^-1 H P H^T counts as positive definite when its smallest eigenvalue is above this of the largest


def ci_weights(p: np.ndarray, r: np.ndarray, first: int = 0) -> np.ndarray:
    """Weights w (K,) of the tracks that minimise det P+ (module docstring), batched numpy.

    p (K, n, n): track covariances; r (K, m, m): covariances of estimates of the state entries
    first .. first + m - 1. Pairs that are not finite and positive definite get w = 1 (the
    estimate is not used): R must be positive definite, and the eigenvalues of R^-1 H P H^T
    must be positive, the smallest above 1e-12 of the largest.
    """
    p, r = np.asarray(p, dtype=float), np.asarray(r, dtype=float)
    n, m = p.shape[-1], r.shape[-1]
    w = np.ones(len(p))
    obs = p[:, first:first + m, first:first + m]
    ok = np.isfinite(obs).all(axis=(1, 2)) & np.isfinite(r).all(axis=(1, 2))
    ok[ok] = np.linalg.eigvalsh(r[ok])[:, 0] > 0.0  # R has a Cholesky factor
    if not ok.any():
        return w
    inv_l = np.linalg.inv(np.linalg.cholesky(r[ok]))  # R = L L^T
    sym = 0.5 * (obs[ok] + obs[ok].transpose(0, 2, 1))
    lam = np.linalg.eigvalsh(inv_l @ sym @ inv_l.transpose(0, 2, 1))  # eigenvalues of R^-1 H P H^T
    pd = lam[:, 0] > _PD_RATIO * np.abs(lam[:, -1])
    w[np.flatnonzero(ok)[pd]] = det_minimising_weights(lam[pd], n - m)
    return w


def _slope(w: np.ndarray, lam: np.ndarray, free: int) -> tuple[np.ndarray, np.ndarray]:
    """g(w) = free / w + sum a / (a w + lambda), a = 1 - lambda, and g'(w), per row (module docstring)."""
    a = 1.0 - lam
    q = a / (a * w[:, None] + lam)
    return q.sum(axis=1) + free / w, -(q * q).sum(axis=1) - free / (w * w)


def det_minimising_weights(lam: np.ndarray, free: int) -> np.ndarray:
    """w (K,) in [W_MIN, 1] of eigenvalues lam (K, m) > 0 and free = n - m unobserved entries: a bound,
    or the root of the decreasing g by safeguarded Newton, row by row (module docstring)."""
    k = len(lam)
    floor, ceiling = _slope(np.full(k, W_MIN), lam, free)[0] <= 0, _slope(np.ones(k), lam, free)[0] >= 0
    w, lo, hi = np.full(k, 0.5), np.full(k, W_MIN), np.ones(k)  # g(lo) > 0 > g(hi)
    active = np.flatnonzero(~(floor | ceiling))
    for _ in range(_MAX_STEPS):
        if not len(active):
            break
        g, dg = _slope(w[active], lam[active], free)
        above = g > 0  # the root lies above w
        lo[active[above]], hi[active[~above]] = w[active[above]], w[active[~above]]
        nxt = w[active] - g / dg
        outside = ~((nxt >= lo[active]) & (nxt <= hi[active]))  # bisect where Newton leaves the bracket
        nxt[outside] = 0.5 * (lo[active[outside]] + hi[active[outside]])
        converged = np.abs(nxt - w[active]) <= W_TOL
        w[active] = nxt
        active = active[~converged]
    w[floor], w[ceiling] = W_MIN, 1.0
    return w


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
    rows[k] of larger x, P (a track table), pair k being (x[rows[k]], P[rows[k]]) with (z[k], R[k], w[k]).

    S = H P H^T / w + R / (1 - w), K = (P / w) H^T S^-1, x+ = x + K (z - H x),
    A = (I - K H) P / w, P+ = A + (K R / (1 - w) - A H^T) K^T (Joseph form, as kalman.update)."""
    z, r, w = np.asarray(z, dtype=float), np.asarray(r, dtype=float), np.asarray(w, dtype=float)
    rows = np.arange(len(z)) if rows is None else np.asarray(rows, dtype=np.int64)
    use = w < 1.0
    rows, z, r, w = rows[use], z[use], r[use], w[use]
    if not len(rows):
        return
    obs = slice(first, first + r.shape[-1])
    pw, rw = p[rows] / w[:, None, None], r / (1.0 - w)[:, None, None]
    gain = np.linalg.solve(pw[:, obs, obs] + rw, pw[:, obs, :]).transpose(0, 2, 1)  # (K, n, m); S symmetric
    x[rows] += (gain @ (z - x[rows, obs])[:, :, None])[:, :, 0]
    a = pw - gain @ pw[:, obs, :]
    p[rows] = a + (gain @ rw - a[:, :, obs]) @ gain.transpose(0, 2, 1)


def ci_fuse_rows(x: np.ndarray, p: np.ndarray, rows: np.ndarray, z: np.ndarray, r: np.ndarray) -> None:
    """CI of the tracks rows (K,) of a table x (N, n), P (N, n, n) with estimates z (K, m), R (K, m, m)
    of their first m state entries, in place: ``ci_weights`` of the K pairs, then ``ci_update_into``."""
    rows = np.asarray(rows, dtype=np.int64)
    ci_update_into(x, p, z, r, ci_weights(p[rows], r), 0, rows)


def ci_fuse_objects_reference(x: np.ndarray, p: np.ndarray, rows: np.ndarray, xy: np.ndarray, cov_xy: np.ndarray,
                              vxy: np.ndarray, cov_vxy: np.ndarray, cols: np.ndarray, velocity: bool) -> None:
    """``ci_fuse_objects`` in numpy: the position-only pairs, then those with a velocity, by ``ci_fuse_rows``."""
    known = cov_vxy[:, 0, 0] + cov_vxy[:, 1, 1] < UNKNOWN_VELOCITY_VAR
    with_v = known.take(cols) if velocity else np.zeros(len(cols), bool)
    for v in (False, True):
        t, d = rows[with_v == v], cols[with_v == v]
        if v:
            r = np.zeros((len(d), 4, 4))
            r[:, :2, :2], r[:, 2:, 2:] = cov_xy.take(d, axis=0), cov_vxy.take(d, axis=0)
            z = np.concatenate([xy.take(d, axis=0), vxy.take(d, axis=0)], axis=1)
        else:
            z, r = xy.take(d, axis=0), cov_xy.take(d, axis=0)
        ci_fuse_rows(x, p, t, z, r)


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
    S = H P H^T / w + R / (1 - w), K = (P / w) H^T S^-1 with S^-1 = L^-T L^-1 (S = L L^T), x+ = x + K (z - H x),
    A = (I - K H) P / w, P+ = A + (K R / (1 - w) - A H^T) K^T (as kalman.update)."""
    n, m = p.shape[0], r.shape[0]
    pw, rw = p / w, r / (1.0 - w)
    s = np.empty((m, m))
    for i in range(m):
        for j in range(m):
            s[i, j] = pw[first + i, first + j] + rw[i, j]
    inv_l = np.empty((m, m))
    _inverse_cholesky(s, inv_l)  # (S is positive definite: R / (1 - w) is, P / w is semi-definite)
    gain = np.zeros((n, m))  # (P / w) H^T L^-T L^-1, L^-1 lower triangular
    for i in range(n):
        for j in range(m):
            acc = 0.0
            for k in range(m):
                s_kj = 0.0
                for q in range(max(k, j), m):
                    s_kj += inv_l[q, k] * inv_l[q, j]
                acc += pw[i, first + k] * s_kj
            gain[i, j] = acc
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


@kernel(OUT_F2, OUT_F3, IN_I1, IN_F2, IN_F3, IN_F2, IN_F3, IN_I1, B1)
def ci_fuse_objects(x: np.ndarray, p: np.ndarray, rows: np.ndarray, xy: np.ndarray, cov_xy: np.ndarray,
                    vxy: np.ndarray, cov_vxy: np.ndarray, cols: np.ndarray, velocity: bool) -> None:
    """CI of the tracks rows (K,) of a table x (N, n), P (N, n, n) with the objects cols (K,) of a list (xy (M, 2),
    cov_xy, vxy, cov_vxy (M, 2, 2)), in place: z = xy, R = cov_xy, or with ``velocity`` where the object measured
    one (trace cov_vxy < UNKNOWN_VELOCITY_VAR, ``ObjectArray.velocity_known``) z = [xy, vxy],
    R = blockdiag(cov_xy, cov_vxy); ``ci_fuse_rows`` of each pair (every weight from the prior covariances): the
    same to rounding as ``ci_fuse_objects_reference``."""
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
        # (R's block as a contiguous copy, the layout _update_pair's S has: one compile of _inverse_cholesky)
        w[k] = _weight(p[rows[k]], r[k, :m, :m].copy(), 0)
    for k in range(n_pairs):
        if w[k] < 1.0:
            m = dim[k]
            _update_pair(x[rows[k]], p[rows[k]], z[k, :m], r[k, :m, :m].copy(), w[k], 0)


def covariance_intersection(x1: np.ndarray, p1: np.ndarray, x2: np.ndarray, p2: np.ndarray,
                            w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Information form of CI for full estimates x1, x2 (K, n), P1, P2 (K, n, n), w (K,) in (0, 1):
    P = (w P1^-1 + (1 - w) P2^-1)^-1, x = P (w P1^-1 x1 + (1 - w) P2^-1 x2) (the reference)."""
    i1, i2 = np.linalg.inv(p1), np.linalg.inv(p2)
    wt = w[:, None, None]
    p = np.linalg.inv(wt * i1 + (1 - wt) * i2)
    info = wt * i1 @ x1[:, :, None] + (1 - wt) * i2 @ x2[:, :, None]
    return (p @ info)[:, :, 0], p
