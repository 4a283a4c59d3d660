"""The generic Kalman filters: Welch & Bishop 2001's random-constant example, FilterPy, and the EKF."""

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter as FilterPyKF

from tests.kalman_reference import ExtendedKalmanFilter, KalmanFilter

# docs/math.md §10, deterministic vectors: (R, k) -> (P_k⁻, K_k, P_k); x̂₀ = 0, P₀ = 1, Q = 1e-5
RANDOM_CONSTANT = {
    (0.01, 1): (1.000010e00, 9.900991e-01, 9.900991e-03), (0.01, 2): (9.910991e-03, 4.977648e-01, 4.977648e-03),
    (0.01, 3): (4.987648e-03, 3.327839e-01, 3.327839e-03), (0.01, 10): (1.144937e-03, 1.027316e-01, 1.027316e-03),
    (0.01, 49): (3.531686e-04, 3.411212e-02, 3.411212e-04), (0.01, 50): (3.511212e-04, 3.392108e-02, 3.392108e-04),
    (1, 1): (1.000010e00, 5.000025e-01, 5.000025e-01), (1, 10): (1.000385e-01, 9.094091e-02, 9.094091e-02),
    (1, 50): (2.017142e-02, 1.977258e-02, 1.977258e-02), (1e-4, 1): (1.000010e00, 9.999000e-01, 9.999000e-05),
    (1e-4, 2): (1.099900e-04, 5.237868e-01, 5.237868e-05), (1e-4, 10): (3.723744e-05, 2.713359e-01, 2.713359e-05),
    (1e-4, 50): (3.701562e-05, 2.701562e-01, 2.701562e-05),
}


@pytest.mark.parametrize("R", [0.01, 1.0, 1e-4])
@pytest.mark.parametrize("joseph", [False, True])
def test_random_constant_recursion_values(R, joseph):
    kf = KalmanFilter(1, 1, joseph=joseph)
    kf.x[:] = 0.0
    kf.P[:] = 1.0
    kf.Q[:] = 1e-5
    kf.R[:] = R
    kf.H[:] = 1.0
    z = -0.37727 + 0.1 * np.random.default_rng(0).standard_normal(50)
    for k in range(1, 51):  # 50 updates: x̂₀ seeds the first prediction (the off-by-one trap of docs/math.md §10)
        kf.predict()
        prior = kf.P[0, 0]
        kf.update(z[k - 1])
        if (R, k) in RANDOM_CONSTANT:
            np.testing.assert_allclose((prior, kf.K[0, 0], kf.P[0, 0]), RANDOM_CONSTANT[(R, k)], rtol=5e-6)
    # steady state, A = H = 1: P⁻∞ = (Q + √(Q² + 4QR))/2
    for _ in range(5000):
        kf.predict()
        kf.update(z[0])
    prior_inf = (1e-5 + np.sqrt(1e-10 + 4e-5 * R)) / 2
    np.testing.assert_allclose(kf.P_prior[0, 0], prior_inf, rtol=1e-9)


def test_linear_kf_equals_filterpy_on_random_systems():
    rng = np.random.default_rng(7)
    for _ in range(20):
        n, m, p = rng.integers(1, 6), rng.integers(1, 4), rng.integers(0, 3)
        ours, theirs = KalmanFilter(n, m, p), FilterPyKF(dim_x=n, dim_z=m, dim_u=p)
        F = np.eye(n) + 0.1 * rng.standard_normal((n, n))
        H = rng.standard_normal((m, n))
        A, C = rng.standard_normal((n, n)), rng.standard_normal((m, m))
        Q, R = 0.01 * A @ A.T + 1e-3 * np.eye(n), C @ C.T + 0.1 * np.eye(m)
        B = rng.standard_normal((n, p)) if p else None
        x0 = rng.standard_normal(n)
        for f in (ours, theirs):
            f.F, f.H, f.Q, f.R = F.copy(), H.copy(), Q.copy(), R.copy()
            f.x = x0.copy() if f is ours else x0.reshape(n, 1).copy()
            f.P = np.eye(n) * 2.0
            if p:
                f.B = B.copy()
        for _ in range(30):
            u = rng.standard_normal(p) if p else None
            z = rng.standard_normal(m)
            ours.predict(u)
            theirs.predict(u=None if u is None else u.reshape(p, 1))
            ours.update(z)
            theirs.update(z.reshape(m, 1))
            np.testing.assert_allclose(ours.x, theirs.x.ravel(), rtol=1e-10, atol=1e-10)
            np.testing.assert_allclose(ours.P, theirs.P, rtol=1e-10, atol=1e-10)
            np.testing.assert_allclose(ours.K, theirs.K, rtol=1e-10, atol=1e-10)


def test_ekf_with_linear_functions_is_the_kf_and_tracks_a_nonlinear_measurement():
    rng = np.random.default_rng(3)
    F = np.array([[1.0, 0.1], [0.0, 1.0]])
    H = np.array([[1.0, 0.0]])
    kf, ekf = KalmanFilter(2, 1), ExtendedKalmanFilter(2, 1)
    for f in (kf, ekf):
        f.F, f.H, f.Q, f.R = F.copy(), H.copy(), 1e-3 * np.eye(2), np.array([[0.05]])
    for _ in range(20):
        z = rng.standard_normal(1)
        kf.predict()
        kf.update(z)
        ekf.predict(lambda x, u: F @ x, lambda x, u: F)
        ekf.update(z, lambda x: H @ x, lambda x: H)
        np.testing.assert_allclose(ekf.x, kf.x, atol=1e-14)
        np.testing.assert_allclose(ekf.P, kf.P, atol=1e-14)
    # range-only measurement of a fixed 2D point from a known moving observer
    target = np.array([2.0, -1.0])
    ekf = ExtendedKalmanFilter(2, 1)
    ekf.x, ekf.P, ekf.Q, ekf.R = np.array([1.0, 0.0]), np.eye(2), 1e-9 * np.eye(2), np.array([[1e-4]])
    for k in range(200):
        observer = np.array([np.cos(0.1 * k), np.sin(0.1 * k)]) * 5
        z = np.linalg.norm(target - observer) + 0.01 * rng.standard_normal()
        ekf.predict(lambda x, u: x, lambda x, u: np.eye(2))
        ekf.update(z, lambda x, o=observer: np.linalg.norm(x - o),
                   lambda x, o=observer: ((x - o) / np.linalg.norm(x - o))[None])
    assert np.linalg.norm(ekf.x - target) < 0.01


def test_bad_input_is_refused():
    kf = KalmanFilter(2, 1)
    with pytest.raises(ValueError, match="non-finite"):
        kf.update(np.array([np.nan]))
    with pytest.raises(ValueError, match="control"):
        kf.predict(np.array([1.0]))
