"""Batched Kalman filters over N tracks, with explicit time steps.

Every track i has a state x_i (n,) and covariance P_i (n, n); a batch is x (N, n),
P (N, n, n). The measurement is always the BEV position z = H x + v, v ~ N(0, R),
with H = [I_2 0] (the first two state entries of every model are x, y in metres).

Motion models (each gives the transition f, its Jacobian F and the process noise Q
over dt seconds; dt may be negative, which predicts backwards):

- ``ConstantVelocity`` (CV): x = [x, y, vx, vy]. Process noise: white-noise
  acceleration, piecewise constant over dt, per axis Q = sigma_a^2 g g^T, g = [dt^2/2, dt].
- ``ConstantAcceleration`` (CA): x = [x, y, vx, vy, ax, ay]. Process noise: white-noise
  jerk, per axis Q = sigma_j^2 g g^T, g = [dt^3/6, dt^2/2, dt].
- ``Ctrv`` (constant turn rate and velocity, an EKF): x = [x, y, v, psi, omega]
  (speed m/s along heading psi rad, turn rate omega rad/s). Process noise on v-dot
  (sigma_a) and omega-dot (sigma_alpha), piecewise constant over dt:
  Q = G diag(sigma_a^2, sigma_alpha^2) G^T with
  G = [[dt^2/2 cos psi, 0], [dt^2/2 sin psi, 0], [dt, 0], [0, dt^2/2], [0, dt]].

Filter equations (all batched):
  predict  x' = f(x), P' = F P F^T + Q                  (F = df/dx at the prior x)
  update   y = z - H x, S = H P H^T + R, K = P H^T S^-1, x+ = x + K y,
           P+ = (I - K H) P (I - K H)^T + K R K^T      (Joseph form, as filterpy)
  gating   d2 = y^T S^-1 y, chi-square with 2 degrees of freedom.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from v2i.core.frames import wrap_angle
from v2i.core.jit import I64, IN_F2, IN_F3, IN_I1, OUT_F2, OUT_F3, kernel

POSITION_DIM = 2
CHI2_2DOF_99 = 9.21  # chi-square 99 % quantile, 2 degrees of freedom


@dataclass(frozen=True)
class StatePrior:
    """Prior standard deviations of what a single position measurement leaves unknown."""

    speed_std_mps: float = 10.0
    accel_std_mps2: float = 3.0
    yaw_std_rad: float = 0.5
    yaw_rate_std_radps: float = 0.5


@dataclass(frozen=True)
class Measured:
    """Detections as filter inputs: xy (K, 2) m, cov_xy (K, 2, 2) m^2, vxy (K, 2) m/s,
    axy (K, 2) m/s^2, yaw (K,) rad, yaw_rate (K,) rad/s; cov_vxy (K, 2, 2) m^2/s^2 the
    velocity covariance (None: no velocity measured)."""

    xy: np.ndarray
    cov_xy: np.ndarray
    vxy: np.ndarray
    axy: np.ndarray
    yaw: np.ndarray
    yaw_rate: np.ndarray
    cov_vxy: np.ndarray | None = None

    def velocity_measured(self, speed_std_mps: float) -> np.ndarray:
        """(K,) True where a velocity was measured more tightly than the prior speed_std^2 I (by trace)."""
        if self.cov_vxy is None:
            return np.zeros(len(self.xy), bool)
        return self.cov_vxy[:, 0, 0] + self.cov_vxy[:, 1, 1] < 2 * speed_std_mps**2

    def velocity_prior(self, speed_std_mps: float) -> np.ndarray:
        """(K, 2, 2) initial velocity covariance: the measured one where it is tighter than
        the prior speed_std^2 I (by trace), else the prior."""
        prior = np.eye(2) * speed_std_mps**2
        if self.cov_vxy is None:
            return np.tile(prior, (len(self.xy), 1, 1))
        out = self.cov_vxy.copy()
        out[~self.velocity_measured(speed_std_mps)] = prior
        return out


class MotionModel(Protocol):
    """What the batched filter needs from a motion model."""

    dim_x: int

    def transition(self, x: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """x' = f(x) (N, n) and F = df/dx, (n, n) shared or (N, n, n) per track."""

    def process_noise(self, x: np.ndarray, dt_s: float) -> np.ndarray:
        """Q, (n, n) shared or (N, n, n) per track, evaluated at the prior x (N, n)."""

    def initial(self, m: Measured, prior: StatePrior) -> tuple[np.ndarray, np.ndarray]:
        """x (K, n) and P (K, n, n) of new tracks from K detections."""

    def velocity(self, x: np.ndarray) -> np.ndarray:
        """Velocity (N, 2) m/s in the map frame."""

    def acceleration(self, x: np.ndarray) -> np.ndarray:
        """Acceleration (N, 2) m/s^2 in the map frame."""

    def yaw_rate(self, x: np.ndarray) -> np.ndarray:
        """Turn rate (N,) rad/s."""

    def velocity_cov(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Covariance (N, 2, 2) m^2/s^2 of the map-frame velocity."""


def _per_axis(block: np.ndarray) -> np.ndarray:
    """kron(block, I_2): state ordered [x, y, d/dt x, d/dt y, ...], the same 1-D block on both axes."""
    k = len(block)
    out = np.zeros((POSITION_DIM * k, POSITION_DIM * k))
    out[0::2, 0::2] = block
    out[1::2, 1::2] = block
    return out


def _diag_prior(m: Measured, variances: list[float]) -> np.ndarray:
    """P (K, n, n): the measured position covariance, then a diagonal of prior variances."""
    k, n = len(m.xy), POSITION_DIM + len(variances)
    p = np.zeros((k, n, n))
    p[:, :2, :2] = m.cov_xy
    idx = np.arange(POSITION_DIM, n)
    p[:, idx, idx] = variances
    return p


def _linear_prior(m: Measured, prior: StatePrior, variances: list[float]) -> np.ndarray:
    """P of the CV / CA state [x, y, vx, vy, ...]: measured position and velocity
    covariances (prior speed std where no velocity was measured), then prior variances."""
    k, n = len(m.xy), 2 * POSITION_DIM + len(variances)
    p = np.zeros((k, n, n))
    p[:, :2, :2] = m.cov_xy
    if variances:
        idx = np.arange(2 * POSITION_DIM, n)
        p[:, idx, idx] = variances
    var = prior.speed_std_mps**2
    unknown = np.array([[var, 0.0], [0.0, var]])  # the prior speed variance on each axis
    if m.cov_vxy is None:  # as velocity_prior: the measured velocity covariance where tighter than the prior
        p[:, 2:4, 2:4] = unknown
    else:
        measured = m.velocity_measured(prior.speed_std_mps)
        every = np.count_nonzero(measured) == k
        p[:, 2:4, 2:4] = m.cov_vxy if every else np.where(measured[:, None, None], m.cov_vxy, unknown)
    return p


@dataclass(frozen=True)
class ConstantVelocity:
    """CV model, x = [x, y, vx, vy]; sigma_a = ``accel_std_mps2`` (white-noise acceleration)."""

    accel_std_mps2: float = 3.0
    dim_x: int = 4

    def transition(self, x: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        f = _per_axis(np.array([[1.0, dt_s], [0.0, 1.0]]))  # p' = p + v dt, v' = v
        return x @ f.T, f

    def process_noise(self, x: np.ndarray, dt_s: float) -> np.ndarray:
        g = np.array([dt_s**2 / 2, dt_s])  # effect of a constant acceleration over dt
        return self.accel_std_mps2**2 * _per_axis(np.outer(g, g))

    def initial(self, m: Measured, prior: StatePrior) -> tuple[np.ndarray, np.ndarray]:
        return np.concatenate([m.xy, m.vxy], axis=1), _linear_prior(m, prior, [])

    def velocity(self, x: np.ndarray) -> np.ndarray:
        return x[:, 2:4]

    def velocity_cov(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return p[:, 2:4, 2:4].copy()

    def acceleration(self, x: np.ndarray) -> np.ndarray:
        return np.zeros((len(x), 2))

    def yaw_rate(self, x: np.ndarray) -> np.ndarray:
        return np.zeros(len(x))


@dataclass(frozen=True)
class ConstantAcceleration:
    """CA model, x = [x, y, vx, vy, ax, ay]; sigma_j = ``jerk_std_mps3`` (white-noise jerk)."""

    jerk_std_mps3: float = 5.0
    dim_x: int = 6

    def transition(self, x: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        # p' = p + v dt + a dt^2 / 2, v' = v + a dt, a' = a
        f = _per_axis(np.array([[1.0, dt_s, dt_s**2 / 2], [0.0, 1.0, dt_s], [0.0, 0.0, 1.0]]))
        return x @ f.T, f

    def process_noise(self, x: np.ndarray, dt_s: float) -> np.ndarray:
        g = np.array([dt_s**3 / 6, dt_s**2 / 2, dt_s])  # effect of a constant jerk over dt
        return self.jerk_std_mps3**2 * _per_axis(np.outer(g, g))

    def initial(self, m: Measured, prior: StatePrior) -> tuple[np.ndarray, np.ndarray]:
        return np.concatenate([m.xy, m.vxy, m.axy], axis=1), _linear_prior(m, prior, [prior.accel_std_mps2**2] * 2)

    def velocity(self, x: np.ndarray) -> np.ndarray:
        return x[:, 2:4]

    def velocity_cov(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return p[:, 2:4, 2:4].copy()

    def acceleration(self, x: np.ndarray) -> np.ndarray:
        return x[:, 4:6]

    def yaw_rate(self, x: np.ndarray) -> np.ndarray:
        return np.zeros(len(x))


def sinc_derivative(u: np.ndarray) -> np.ndarray:
    """d/du (sin u / u); Taylor series -u/3 + u^3/30 near 0, where the closed form cancels."""
    u = np.asarray(u, dtype=float)
    small = np.abs(u) < 1e-3
    safe = np.where(small, 1.0, u)
    exact = (safe * np.cos(safe) - np.sin(safe)) / safe**2
    return np.where(small, -u / 3 + u**3 / 30, exact)


@dataclass(frozen=True)
class Ctrv:
    """CTRV model (EKF), x = [x, y, v, psi, omega].

    Chord form of the turn, exact for any omega and smooth through omega = 0: with
    u = omega dt / 2 and s(u) = sin(u) / u,
      x' = x + v dt s(u) cos(psi + u),  y' = y + v dt s(u) sin(psi + u),
      v' = v, psi' = psi + omega dt (wrapped), omega' = omega,
    which equals the textbook x' = x + v/omega (sin(psi + omega dt) - sin psi) for omega != 0
    and the straight line x' = x + v dt cos psi for omega = 0.
    """

    accel_std_mps2: float = 3.0  # sigma_a, white noise on v-dot
    yaw_accel_std_radps2: float = 1.0  # sigma_alpha, white noise on omega-dot
    dim_x: int = 5

    def transition(self, x: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        v, psi, omega = x[:, 2], x[:, 3], x[:, 4]
        u = 0.5 * omega * dt_s
        s, ds = np.sinc(u / np.pi), sinc_derivative(u)  # np.sinc(t) = sin(pi t) / (pi t)
        chord = v * dt_s * s
        c, sn = np.cos(psi + u), np.sin(psi + u)
        x_new = x.copy()
        x_new[:, 0] += chord * c
        x_new[:, 1] += chord * sn
        x_new[:, 3] = wrap_angle(psi + omega * dt_s)
        f = np.broadcast_to(np.eye(5), (len(x), 5, 5)).copy()
        f[:, 0, 2], f[:, 1, 2] = dt_s * s * c, dt_s * s * sn  # d/dv
        f[:, 0, 3], f[:, 1, 3] = -chord * sn, chord * c  # d/dpsi
        f[:, 0, 4] = v * dt_s**2 / 2 * (ds * c - s * sn)  # d/domega, du/domega = dt / 2
        f[:, 1, 4] = v * dt_s**2 / 2 * (ds * sn + s * c)
        f[:, 3, 4] = dt_s
        return x_new, f

    def process_noise(self, x: np.ndarray, dt_s: float) -> np.ndarray:
        g = np.zeros((len(x), 5, 2))
        g[:, 0, 0] = dt_s**2 / 2 * np.cos(x[:, 3])
        g[:, 1, 0] = dt_s**2 / 2 * np.sin(x[:, 3])
        g[:, 2, 0], g[:, 3, 1], g[:, 4, 1] = dt_s, dt_s**2 / 2, dt_s
        g[:, :, 0] *= self.accel_std_mps2
        g[:, :, 1] *= self.yaw_accel_std_radps2
        return g @ g.transpose(0, 2, 1)  # Q = G diag(sigma^2) G^T

    def initial(self, m: Measured, prior: StatePrior) -> tuple[np.ndarray, np.ndarray]:
        speed = np.hypot(m.vxy[:, 0], m.vxy[:, 1])
        # heading from the velocity when it says something, else from the box
        psi = np.where(speed > 0.5, np.arctan2(m.vxy[:, 1], m.vxy[:, 0]), m.yaw)
        x = np.column_stack([m.xy, speed, wrap_angle(psi), m.yaw_rate])
        var = [prior.speed_std_mps**2, prior.yaw_std_rad**2, prior.yaw_rate_std_radps**2]
        return x, _diag_prior(m, var)

    def velocity(self, x: np.ndarray) -> np.ndarray:
        return x[:, 2:3] * np.column_stack([np.cos(x[:, 3]), np.sin(x[:, 3])])

    def velocity_cov(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        # v_xy = v [cos psi, sin psi]: J = d v_xy / d(v, psi) = [[c, -v s], [s, v c]], C = J P J^T
        c, s, v = np.cos(x[:, 3]), np.sin(x[:, 3]), x[:, 2]
        j = np.stack([np.stack([c, -v * s], -1), np.stack([s, v * c], -1)], -2)
        return j @ p[:, 2:4, 2:4] @ j.transpose(0, 2, 1)

    def acceleration(self, x: np.ndarray) -> np.ndarray:
        # centripetal: a = v omega, perpendicular to the heading
        return (x[:, 2] * x[:, 4])[:, None] * np.column_stack([-np.sin(x[:, 3]), np.cos(x[:, 3])])

    def yaw_rate(self, x: np.ndarray) -> np.ndarray:
        return x[:, 4].copy()


def two_point(model: MotionModel, x0: np.ndarray, p0: np.ndarray, z: np.ndarray, r: np.ndarray,
              dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Two-point initialisation of K tracks of a linear model with x = [p, v, rest] (CV, CA).

    Each track was born dt_s (!= 0) seconds ago as x0 (K, n), P0 (K, n, n) from a position
    without a measured velocity; z (K, 2), R (K, 2, 2) is its second position. Returns the
    state x (K, n), P (K, n, n) at the second position's time with the velocity prior dropped
    (flat): the limit of predict + update as the prior velocity variance goes to infinity.

    Derivation: x2 = F x1 + w, w ~ N(0, Q); z = H x2 + n, n ~ N(0, R); p1 ~ N(z1, R1) and
    the rest r1 as born; v1 unknown. H F x1 = F_pp p1 + F_pv v1 + F_pr r1 gives
    v1 = F_pv^-1 (z - n - H w - F_pp p1 - F_pr r1), so with G = F[:, v] F_pv^-1:
      x2 = G z + A x1 + B w - G n,   A = F - G H F (its velocity columns vanish), B = I - G H
      x = G z + A x0,                P = A P0 A^T + G R G^T + B Q B^T
    For CV (F_pv = dt I): p = z, v = (z - z1) / dt, P_pp = R, P_pv = R / dt,
    P_vv = (R1 + R) / dt^2 + sigma_a^2 dt^2 / 4 (the last term: v2 is the end-point velocity,
    (z - z1) / dt the mean one, which lags it by a dt / 2 under the white acceleration a).
    """
    if not isinstance(model, (ConstantVelocity, ConstantAcceleration)):
        raise ValueError(f"two-point initialisation needs a linear model with a velocity state, got {model!r}")
    _, f = model.transition(x0, dt_s)  # (n, n), shared by the batch
    q = model.process_noise(x0, dt_s)
    g = f[:, 2:4] @ np.linalg.inv(f[:2, 2:4])  # G = F[:, v] F_pv^-1, (n, 2)
    a = f - g @ f[:2, :]  # A = F - G H F
    b = np.eye(model.dim_x)
    b[:, :2] -= g  # B = I - G H
    x = z @ g.T + x0 @ a.T
    p = a @ p0 @ a.T + g @ r @ g.T + b @ q @ b.T
    return x, p


def predict(x: np.ndarray, p: np.ndarray, model: MotionModel, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Prior x (N, n), P (N, n, n) -> predicted x, P after dt_s seconds (new arrays)."""
    if isinstance(model, (ConstantVelocity, ConstantAcceleration)) and dt_s:  # F, Q depend on dt alone
        f, q = _linear_matrices(model, dt_s)
        return x @ f.T, _sandwich(f, p) + q
    q = model.process_noise(x, dt_s)  # Q at the prior state
    x_new, f = model.transition(x, dt_s)
    # P' = F P F^T + Q
    if f.ndim == 2:  # one F for every track: two matrix products over the whole batch
        return x_new, _sandwich(f, p) + q
    return x_new, f @ p @ np.swapaxes(f, -1, -2) + q


_LINEAR: dict[tuple[object, float], tuple[np.ndarray, np.ndarray]] = {}  # (model, dt_s) -> read-only F, Q


def _linear_matrices(model: ConstantVelocity | ConstantAcceleration, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """F (n, n) and Q (n, n) of a linear model (CV, CA) over dt_s != 0, kept per (model, dt_s): a tracker
    predicts over the same few cycle periods again and again (0.0 is left out: -0.0 hashes as 0.0)."""
    key = (model, dt_s)
    found = _LINEAR.get(key)
    if found is None:
        if len(_LINEAR) >= 256:
            _LINEAR.clear()
        f, q = model.transition(np.zeros((0, model.dim_x)), dt_s)[1], model.process_noise(None, dt_s)
        f.flags.writeable = q.flags.writeable = False
        found = _LINEAR[key] = (f, q)
    return found


def _sandwich(f: np.ndarray, p: np.ndarray) -> np.ndarray:
    """F P_i F^T (N, n, n) for one F (n, n) and P (N, n, n): F [P_1 .. P_N] as one (n, N n) product,
    then the rows of all F P_i times F^T as one (N n, n) product (a stacked f @ p is several times slower)."""
    k, n = len(p), f.shape[0]
    fp = (f @ p.transpose(1, 0, 2).reshape(n, k * n)).reshape(n, k, n).transpose(1, 0, 2)  # (N, n, n): F P_i
    return (fp.reshape(k * n, n) @ f.T).reshape(k, n, n)


def update(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray, first: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Paired update of K tracks with K measurements of two consecutive state entries (Joseph form).

    ``first`` = 0 measures the position (H = [I_2 0]); ``first`` = 2 measures the velocity
    of the CV and CA models (H = [0 I_2 0]). x (K, n), P (K, n, n), z (K, 2), R (K, 2, 2)
    -> posterior x (K, n), P (K, n, n) and the innovation covariance S (K, 2, 2).
    Inputs are not modified.
    """
    x_post, p_post = np.array(x, dtype=float), np.array(p, dtype=float)
    z, r = np.asarray(z, dtype=float), np.asarray(r, dtype=float)
    pairs = np.arange(len(x_post))
    s = p_post[:, first:first + 2, first:first + 2] + r  # S = H P H^T + R
    update_rows(x_post, p_post, pairs, z, r, pairs, first)
    return x_post, p_post, s


@kernel(OUT_F2, OUT_F3, IN_I1, IN_F2, IN_F3, IN_I1, I64)
def update_rows(x: np.ndarray, p: np.ndarray, rows: np.ndarray, z: np.ndarray, r: np.ndarray, cols: np.ndarray,
                first: int) -> None:
    """In place, the paired update of the tracks rows (K,) of x (N, n), P (N, n, n) with the measurements
    cols (K,) of z (M, 2), R (M, 2, 2) of the state entries first, first + 1 (a compiled loop, ``update``):

        S = H P H^T + R,  K = P H^T S^-1 (S^-1 = [[d, -b], [-c, a]] / (a d - b c)),  x+ = x + K (z - H x),
        Joseph form P+ = (I - K H) P (I - K H)^T + K R K^T, expanded so that only (n, 2) products
        remain: with A = (I - K H) P = P - K (H P), A (I - K H)^T = A - (A H^T) K^T, so
        P+ = A + (K R - A H^T) K^T.
    """
    n = x.shape[1]
    gain, b = np.empty((n, 2)), np.empty((n, 2))
    for k in range(rows.shape[0]):
        i, j = rows[k], cols[k]
        xi, pi, rj = x[i], p[i], r[j]
        a00, a01 = pi[first, first] + rj[0, 0], pi[first, first + 1] + rj[0, 1]
        a10, a11 = pi[first + 1, first] + rj[1, 0], pi[first + 1, first + 1] + rj[1, 1]
        det = a00 * a11 - a01 * a10
        i00, i01, i10, i11 = a11 / det, -a01 / det, -a10 / det, a00 / det
        for q in range(n):
            gain[q, 0] = pi[q, first] * i00 + pi[q, first + 1] * i10
            gain[q, 1] = pi[q, first] * i01 + pi[q, first + 1] * i11
        y0, y1 = z[j, 0] - xi[first], z[j, 1] - xi[first + 1]
        for q in range(n):
            xi[q] += gain[q, 0] * y0 + gain[q, 1] * y1
        for q in range(n):  # A = P - K (H P), in place: row q of K H P needs only rows first, first + 1 of P,
            for c in range(n):  # which are overwritten last
                if q != first and q != first + 1:
                    pi[q, c] -= gain[q, 0] * pi[first, c] + gain[q, 1] * pi[first + 1, c]
        for c in range(n):
            h0, h1 = pi[first, c], pi[first + 1, c]
            pi[first, c] = h0 - (gain[first, 0] * h0 + gain[first, 1] * h1)
            pi[first + 1, c] = h1 - (gain[first + 1, 0] * h0 + gain[first + 1, 1] * h1)
        for q in range(n):  # B = K R - A H^T
            b[q, 0] = gain[q, 0] * rj[0, 0] + gain[q, 1] * rj[1, 0] - pi[q, first]
            b[q, 1] = gain[q, 0] * rj[0, 1] + gain[q, 1] * rj[1, 1] - pi[q, first + 1]
        for q in range(n):  # P+ = A + B K^T
            for c in range(n):
                pi[q, c] += b[q, 0] * gain[c, 0] + b[q, 1] * gain[c, 1]


def _quadratic_form(y0, y1, a, b, c, d):
    """y^T S^-1 y for S = [[a, b], [c, d]] (any broadcastable shapes): (d y0^2 - (b + c) y0 y1 + a y1^2) / det S."""
    return (d * y0 * y0 - (b + c) * y0 * y1 + a * y1 * y1) / (a * d - b * c)


def mahalanobis_sq(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance d2 (N, M) of every track to every measurement.

    x (N, n), P (N, n, n), z (M, 2), R (M, 2, 2); d2_ij = y^T S^-1 y with
    y = z_j - H x_i and S_ij = H P_i H^T + R_j (closed-form 2 x 2 inverse).
    """
    pp, rr = p[:, None, :2, :2], r[None, :, :, :]
    s = pp + rr  # S_ij = H P_i H^T + R_j, (N, M, 2, 2)
    y0, y1 = z[None, :, 0] - x[:, None, 0], z[None, :, 1] - x[:, None, 1]
    return _quadratic_form(y0, y1, s[..., 0, 0], s[..., 0, 1], s[..., 1, 0], s[..., 1, 1])


def make_model(name: str, accel_std_mps2: float, jerk_std_mps3: float, yaw_accel_std_radps2: float) -> MotionModel:
    """Motion model by name: ``cv``, ``ca`` or ``ctrv``."""
    if name == "cv":
        return ConstantVelocity(accel_std_mps2)
    if name == "ca":
        return ConstantAcceleration(jerk_std_mps3)
    if name == "ctrv":
        return Ctrv(accel_std_mps2, yaw_accel_std_radps2)
    raise ValueError(f"motion must be one of 'cv', 'ca', 'ctrv', got {name!r}")
