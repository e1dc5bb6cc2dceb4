"""The batched Kalman filters against filterpy, the CTRV model's closed forms, and NEES consistency."""

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter, KalmanFilter
from scipy.stats import chi2

from v2i.fusion import kalman
from v2i.fusion.kalman import (
    ConstantAcceleration,
    ConstantVelocity,
    Ctrv,
    Measured,
    StatePrior,
)

N_TRACKS = 4
STEPS = 1000


def random_spd(rng, k, scale=0.5):
    a = rng.normal(0, scale, (k, 2, 2))
    return a @ a.transpose(0, 2, 1) + 0.05 * np.eye(2)


def start(model, rng, n=N_TRACKS):
    m = Measured(xy=rng.normal(0, 10, (n, 2)), cov_xy=random_spd(rng, n), vxy=rng.normal(0, 5, (n, 2)),
                 axy=rng.normal(0, 1, (n, 2)), yaw=rng.uniform(-np.pi, np.pi, n), yaw_rate=rng.normal(0, 0.2, n))
    return model.initial(m, StatePrior())


def filterpy_kf(model, x0, p0):
    kf = KalmanFilter(dim_x=model.dim_x, dim_z=2)
    kf.x, kf.P = x0.copy()[:, None], p0.copy()
    kf.H = np.hstack([np.eye(2), np.zeros((2, model.dim_x - 2))])
    return kf


def drive_linear(model, seed):
    """1000 random-dt predicts and random-subset updates, batched and in filterpy, compared each step."""
    rng = np.random.default_rng(seed)
    x, p = start(model, rng)
    ref = [filterpy_kf(model, x[i], p[i]) for i in range(N_TRACKS)]
    for _ in range(STEPS):
        dt = rng.uniform(0.01, 0.3)
        x, p = kalman.predict(x, p, model, dt)
        f, q = model.transition(np.zeros((1, model.dim_x)), dt)[1], model.process_noise(x, dt)
        for kf in ref:
            kf.predict(F=f, Q=q)
        idx = np.flatnonzero(rng.random(N_TRACKS) < 0.7)
        z, r = x[idx, :2] + rng.normal(0, 1.0, (len(idx), 2)), random_spd(rng, len(idx))
        d2 = kalman.mahalanobis_sq(x[idx], p[idx], z, r)
        x[idx], p[idx], s = kalman.update(x[idx], p[idx], z, r)
        for j, i in enumerate(idx):
            ref[i].update(z[j], R=r[j])
            np.testing.assert_allclose(s[j], ref[i].S, rtol=0, atol=1e-9)
            assert d2[j, j] == pytest.approx(ref[i].mahalanobis**2, rel=1e-9)
        np.testing.assert_allclose(x, np.hstack([kf.x for kf in ref]).T, rtol=0, atol=1e-9)
        np.testing.assert_allclose(p, np.stack([kf.P for kf in ref]), rtol=0, atol=1e-9)


def test_batched_cv_equals_filterpy_kalman_filter():
    drive_linear(ConstantVelocity(accel_std_mps2=2.0), seed=1)


def test_batched_ca_equals_filterpy_kalman_filter():
    drive_linear(ConstantAcceleration(jerk_std_mps3=4.0), seed=2)


class CtrvEkf(ExtendedKalmanFilter):
    """filterpy's EKF with the CTRV motion f(x) of one track; F and Q are set before each predict."""

    def __init__(self, model, x0, p0, dt_s):
        super().__init__(dim_x=5, dim_z=2)
        self.model, self.dt_s = model, dt_s
        self.x, self.P = x0.copy()[:, None], p0.copy()

    def predict_x(self, u=0):
        self.x = self.model.transition(self.x.T, self.dt_s)[0].T


def test_batched_ctrv_ekf_equals_filterpy_extended_kalman_filter():
    rng = np.random.default_rng(3)
    model = Ctrv(accel_std_mps2=1.5, yaw_accel_std_radps2=0.3)
    truth = np.column_stack([rng.normal(0, 10, (N_TRACKS, 2)), [10.0, 5.0, 14.0, 2.0], [0.0, 1.0, -2.0, 3.0],
                             [0.3, 0.0, -0.2, 1e-9]])
    x, p = truth + rng.normal(0, 0.1, truth.shape), np.tile(np.diag([0.5, 0.5, 4.0, 0.2, 0.1]), (N_TRACKS, 1, 1))
    ref = [CtrvEkf(model, x[i], p[i], 0.0) for i in range(N_TRACKS)]
    h = np.hstack([np.eye(2), np.zeros((2, 3))])
    for _ in range(STEPS):
        dt = rng.uniform(0.01, 0.3)
        truth = model.transition(truth, dt)[0]
        for i, ekf in enumerate(ref):
            ekf.dt_s, ekf.F = dt, model.transition(ekf.x.T, dt)[1][0]  # Jacobian at the prior
            ekf.Q = model.process_noise(ekf.x.T, dt)[0]
            ekf.predict()
        x, p = kalman.predict(x, p, model, dt)
        idx = np.flatnonzero(rng.random(N_TRACKS) < 0.7)
        z, r = truth[idx, :2] + rng.normal(0, 0.3, (len(idx), 2)), random_spd(rng, len(idx), 0.3)
        x[idx], p[idx], _ = kalman.update(x[idx], p[idx], z, r)
        for j, i in enumerate(idx):
            ref[i].update(z[j][:, None], HJacobian=lambda _x: h, Hx=lambda s: h @ s, R=r[j])
        np.testing.assert_allclose(x, np.hstack([ekf.x for ekf in ref]).T, rtol=0, atol=1e-9)
        np.testing.assert_allclose(p, np.stack([ekf.P for ekf in ref]), rtol=0, atol=1e-9)
    assert np.abs(x[:, :2] - truth[:, :2]).max() < 2.0  # and the filter actually tracks the turns


def test_ctrv_chord_form_equals_textbook_turn_and_straight_line():
    model, dt = Ctrv(), 0.4
    x = np.array([[1.0, 2.0, 12.0, 0.7, 0.5], [1.0, 2.0, 12.0, 0.7, -1.3], [1.0, 2.0, 12.0, 0.7, 0.0]])
    nxt = model.transition(x, dt)[0]
    for row, out in zip(x[:2], nxt[:2]):
        px, py, v, psi, w = row
        assert out[0] == pytest.approx(px + v / w * (np.sin(psi + w * dt) - np.sin(psi)), abs=1e-12)
        assert out[1] == pytest.approx(py + v / w * (np.cos(psi) - np.cos(psi + w * dt)), abs=1e-12)
    np.testing.assert_allclose(nxt[2, :2], [1 + 12 * dt * np.cos(0.7), 2 + 12 * dt * np.sin(0.7)], atol=1e-12)
    assert nxt[2, 3] == pytest.approx(0.7) and nxt[0, 3] == pytest.approx(0.7 + 0.5 * dt)


@pytest.mark.parametrize("omega", [0.0, 1e-9, 1e-5, -4e-3, 0.8, -2.5])
def test_ctrv_jacobian_matches_finite_differences(omega):
    model, dt, eps = Ctrv(), 0.3, 1e-6
    x = np.array([[3.0, -1.0, 9.0, 2.0, omega]])
    f = model.transition(x, dt)[1][0]
    numeric = np.empty((5, 5))
    for j in range(5):
        step = np.zeros((1, 5))
        step[0, j] = eps
        hi, lo = model.transition(x + step, dt)[0][0], model.transition(x - step, dt)[0][0]
        numeric[:, j] = (hi - lo) / (2 * eps)
    np.testing.assert_allclose(f, numeric, atol=1e-7)


def test_sinc_derivative_is_continuous_at_the_series_switch():
    u = np.array([-1e-3 - 1e-12, -1e-3 + 1e-12, 1e-3 - 1e-12, 1e-3 + 1e-12, 0.0])
    d = kalman.sinc_derivative(u)
    assert d[0] == pytest.approx(d[1], abs=1e-10) and d[2] == pytest.approx(d[3], abs=1e-10) and d[4] == 0.0


def test_process_noise_is_symmetric_positive_semidefinite():
    rng = np.random.default_rng(4)
    for model in (ConstantVelocity(), ConstantAcceleration(), Ctrv()):
        x = rng.normal(0, 3, (6, model.dim_x))
        for dt in (0.05, 0.5, -0.2):
            q = np.broadcast_to(model.process_noise(x, dt), (6, model.dim_x, model.dim_x))
            np.testing.assert_allclose(q, q.transpose(0, 2, 1), atol=1e-15)
            assert np.linalg.eigvalsh(q).min() > -1e-12


def test_mahalanobis_matrix_matches_per_pair_inverse():
    rng = np.random.default_rng(5)
    x, p = start(ConstantVelocity(), rng, n=7)
    z, r = rng.normal(0, 10, (5, 2)), random_spd(rng, 5)
    d2 = kalman.mahalanobis_sq(x, p, z, r)
    assert d2.shape == (7, 5)
    for i in range(7):
        for j in range(5):
            y = z[j] - x[i, :2]
            assert d2[i, j] == pytest.approx(y @ np.linalg.inv(p[i, :2, :2] + r[j]) @ y, rel=1e-12)


def test_cv_filter_nees_is_chi_square_consistent():
    """Monte-Carlo NEES (Bar-Shalom): truth drawn from the CV model itself, 400 runs batched as tracks."""
    rng = np.random.default_rng(6)
    runs, steps, model, r_std = 400, 150, ConstantVelocity(accel_std_mps2=1.5), 0.7
    p0 = np.tile(np.diag([r_std**2, r_std**2, 4.0, 4.0]), (runs, 1, 1))
    truth = np.tile([0.0, 0.0, 10.0, 2.0], (runs, 1))
    x = truth + np.einsum("nij,nj->ni", np.linalg.cholesky(p0), rng.normal(size=(runs, 4)))
    p, r = p0.copy(), np.tile(np.eye(2) * r_std**2, (runs, 1, 1))
    anees = []
    for _ in range(steps):
        dt = rng.uniform(0.05, 0.2)
        w = rng.multivariate_normal(np.zeros(4), model.process_noise(truth, dt), runs)
        truth = model.transition(truth, dt)[0] + w
        x, p = kalman.predict(x, p, model, dt)
        x, p, _ = kalman.update(x, p, truth[:, :2] + rng.normal(0, r_std, (runs, 2)), r)
        e = truth - x
        anees.append(np.mean(np.einsum("ni,nij,nj->n", e, np.linalg.inv(p), e)))
    lo, hi = chi2.ppf([0.005, 0.995], 4 * runs) / runs  # 99 % interval of the run-averaged NEES
    anees = np.array(anees)
    assert np.mean((anees > lo) & (anees < hi)) >= 0.95
    assert lo < anees.mean() < hi


def test_make_model_rejects_unknown_names():
    assert isinstance(kalman.make_model("ca", 1, 2, 3), ConstantAcceleration)
    with pytest.raises(ValueError, match="motion"):
        kalman.make_model("bicycle", 1, 2, 3)


@pytest.mark.parametrize("model", [ConstantVelocity(2.0), ConstantAcceleration(4.0)], ids=["cv", "ca"])
def test_velocity_update_equals_filterpy_with_velocity_selector(model):
    rng = np.random.default_rng(5)
    x, p = start(model, rng)
    z, r = rng.normal(0, 5, (N_TRACKS, 2)), random_spd(rng, N_TRACKS)
    x_post, p_post, _ = kalman.update(x, p, z, r, first=2)
    for i in range(N_TRACKS):
        kf = filterpy_kf(model, x[i], p[i])
        kf.H = np.roll(kf.H, 2, axis=1)  # H = [0 I_2 0]
        kf.update(z[i], R=r[i])
        np.testing.assert_allclose(x_post[i], kf.x[:, 0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(p_post[i], kf.P, rtol=0, atol=1e-9)


@pytest.mark.parametrize("model", [ConstantVelocity(), ConstantAcceleration(), Ctrv()], ids=["cv", "ca", "ctrv"])
def test_velocity_covariance_is_the_linearised_covariance_of_the_velocity(model):
    rng = np.random.default_rng(6)
    x, p = start(model, rng)
    x[:, :] += rng.normal(0, 0.1, x.shape)
    eps = 1e-6
    for i in range(N_TRACKS):  # C = J P J^T with J = d velocity / d x by central differences
        j = np.column_stack([(model.velocity((x[i] + eps * e)[None]) - model.velocity((x[i] - eps * e)[None]))[0]
                             / (2 * eps) for e in np.eye(model.dim_x)])
        np.testing.assert_allclose(model.velocity_cov(x[i:i + 1], p[i:i + 1])[0], j @ p[i] @ j.T, rtol=1e-6, atol=1e-9)


def test_new_tracks_take_a_measured_velocity_covariance_tighter_than_the_prior():
    rng = np.random.default_rng(7)
    tight, loose = np.eye(2) * 0.09, np.eye(2) * 1e4
    m = Measured(xy=np.zeros((2, 2)), cov_xy=random_spd(rng, 2), vxy=np.ones((2, 2)), axy=np.zeros((2, 2)),
                 yaw=np.zeros(2), yaw_rate=np.zeros(2), cov_vxy=np.stack([tight, loose]))
    for model in (ConstantVelocity(), ConstantAcceleration()):
        _, p = model.initial(m, StatePrior(speed_std_mps=10.0))
        np.testing.assert_array_equal(p[0, 2:4, 2:4], tight)
        np.testing.assert_array_equal(p[1, 2:4, 2:4], np.eye(2) * 100.0)
        np.testing.assert_array_equal(p[:, :2, :2], m.cov_xy)


# --- two-point initialisation -------------------------------------------------------------------


def filterpy_with_velocity_prior(model, x0, p0, z, r, dt_s, velocity_var):
    """filterpy: born at x0, P0 with the velocity variance replaced by velocity_var, predict dt_s, update z."""
    p = p0.copy()
    p[2:4, :], p[:, 2:4] = 0.0, 0.0
    p[2:4, 2:4] = np.eye(2) * velocity_var
    kf = filterpy_kf(model, x0, p)
    xs = x0[None]
    kf.predict(F=model.transition(xs, dt_s)[1], Q=model.process_noise(xs, dt_s))
    kf.update(z, R=r)
    return kf.x[:, 0], kf.P


@pytest.mark.parametrize("model", [ConstantVelocity(3.0), ConstantAcceleration(5.0)], ids=["cv", "ca"])
def test_two_point_is_the_kalman_filter_with_a_flat_velocity_prior(model):
    """filterpy's predict + update converge to the closed form as the prior velocity variance L grows (error ~ 1/L)."""
    rng = np.random.default_rng(3)
    x0, p0 = start(model, rng)
    z, r, dt_s = x0[:, :2] + rng.normal(0, 3, (N_TRACKS, 2)), random_spd(rng, N_TRACKS), 0.2
    x, p = kalman.two_point(model, x0, p0, z, r, dt_s)
    for i in range(N_TRACKS):
        errors = []
        for velocity_var in (1e4, 1e6, 1e8):
            xf, pf = filterpy_with_velocity_prior(model, x0[i], p0[i], z[i], r[i], dt_s, velocity_var)
            errors.append(max(np.abs(xf - x[i]).max(), np.abs(pf - p[i]).max()))
        assert errors[2] < 1e-3 and 30 < errors[0] / errors[1] < 300 and 30 < errors[1] / errors[2] < 300, errors
        np.testing.assert_allclose(p[i], p[i].T, atol=1e-12)
        assert np.all(np.linalg.eigvalsh(p[i]) > 0)


def test_two_point_cv_closed_form():
    """p = z2, v = (z2 - z1) / dt; P_pp = R2, P_pv = R2 / dt, P_vv = (R1 + R2) / dt^2 + sigma_a^2 dt^2 / 4."""
    rng = np.random.default_rng(5)
    model, dt_s = ConstantVelocity(2.0), 0.25
    x0, p0 = start(model, rng)
    z1, r1 = x0[:, :2], p0[:, :2, :2]
    z2, r2 = z1 + rng.normal(0, 3, (N_TRACKS, 2)), random_spd(rng, N_TRACKS)
    x, p = kalman.two_point(model, x0, p0, z2, r2, dt_s)
    np.testing.assert_allclose(x[:, :2], z2, atol=1e-12)
    np.testing.assert_allclose(x[:, 2:], (z2 - z1) / dt_s, atol=1e-12)
    np.testing.assert_allclose(p[:, :2, :2], r2, atol=1e-12)
    np.testing.assert_allclose(p[:, :2, 2:], r2 / dt_s, atol=1e-12)
    np.testing.assert_allclose(p[:, 2:, 2:], (r1 + r2) / dt_s**2 + np.eye(2) * 2.0**2 * dt_s**2 / 4, atol=1e-9)


def test_two_point_needs_a_linear_model_with_a_velocity_state():
    rng = np.random.default_rng(0)
    x0, p0 = start(Ctrv(), rng)
    with pytest.raises(ValueError, match="linear"):
        kalman.two_point(Ctrv(), x0, p0, x0[:, :2], p0[:, :2, :2], 0.1)


@pytest.mark.parametrize("n_tracks", [0, 1, 7, 300])
def test_shared_transition_sandwich_equals_the_stacked_product(n_tracks):
    """kalman.predict's F P F^T as two whole-batch products equals F @ P_i @ F^T track by track."""
    rng = np.random.default_rng(n_tracks)
    a = rng.normal(size=(n_tracks, 6, 6))
    p = a @ np.swapaxes(a, -1, -2)
    _, f = kalman.ConstantAcceleration(2.0).transition(np.zeros((n_tracks, 6)), 0.1)
    expected = np.array([f @ p_i @ f.T for p_i in p]).reshape(n_tracks, 6, 6)
    np.testing.assert_allclose(kalman._sandwich(f, p), expected, rtol=1e-14, atol=1e-12)
