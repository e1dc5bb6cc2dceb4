"""kalman.predict of the linear models (CV, CA) takes F and Q kept per (model, dt): the same bits as the
model's transition and process noise computed afresh, on the first call and on the calls that reuse them."""

import numpy as np
import pytest

from v2i.fusion import kalman


def _reference(x, p, model, dt_s):
    """The predict of the models' own matrices (the path before the kept F, Q)."""
    q = model.process_noise(x, dt_s)
    x_new, f = model.transition(x, dt_s)
    return x_new, kalman._sandwich(f, p) + q


@pytest.mark.parametrize("name", ["cv", "ca"])
def test_predict_with_kept_matrices_equals_the_fresh_ones_bit_for_bit(name):
    rng = np.random.default_rng(3)
    model = kalman.make_model(name, 1.3, 4.0, 1.0)
    n = model.dim_x
    for dt_s in (0.09999999999999964, 0.1, 0.10000000000000142, -0.25, 1e-9, 0.09999999999999964):
        for rows in (0, 1, 7):
            x, a = rng.normal(size=(rows, n)) * 30.0, rng.normal(size=(rows, n, n))
            p = a @ a.transpose(0, 2, 1)
            got, want = kalman.predict(x, p, model, dt_s), _reference(x, p, model, dt_s)
            for g, w in zip(got, want):
                assert g.shape == w.shape and g.tobytes() == w.tobytes()


def test_kept_matrices_are_per_model_and_read_only():
    cv1, cv2 = kalman.make_model("cv", 1.0, 5.0, 1.0), kalman.make_model("cv", 3.0, 5.0, 1.0)
    f1, q1 = kalman._linear_matrices(cv1, 0.1)
    f2, q2 = kalman._linear_matrices(cv2, 0.1)
    assert np.array_equal(f1, f2) and not np.array_equal(q1, q2)  # sigma_a enters Q only
    assert kalman._linear_matrices(cv1, 0.1)[1] is q1  # kept
    with pytest.raises(ValueError):
        q1[0, 0] = 0.0
