"""The small compiled linear-algebra kernels (ivc.linalg) against NumPy."""

import numba
import numpy as np
import pytest

from ivc import linalg as la


@numba.njit(cache=True)
def _factor_and_solve(S):
    n = S.shape[0]
    L = np.zeros((n, n))
    ok = la.cholesky(S, n, L)
    x = np.zeros(n)
    if ok:
        la.cholesky_solve(L, n, np.ones(n), x)
    return ok, L, x, la.cholesky_logdet(L, n) if ok else 0.0


@numba.njit(cache=True)
def _update(L, PHt, nu, xp, Pp, in_place):
    n, m = PHt.shape
    U = np.zeros((n, m))
    if in_place:  # x, P over xp, Pp and w over nu, as the filters call it
        maha = la.factored_update(L, PHt, nu, xp, Pp, n, m, U, nu, xp, Pp)
        return maha, xp, Pp
    x, P, w = np.full(n, np.nan), np.full((n, n), np.nan), np.zeros(m)
    maha = la.factored_update(L, PHt, nu, xp, Pp, n, m, U, w, x, P)
    return maha, x, P


@pytest.mark.parametrize("n", [1, 3, 4, 6, 7])
def test_cholesky_solve_and_logdet_match_numpy(rng, n):
    A = rng.normal(size=(n, n))
    S = A @ A.T + 0.1 * np.eye(n)
    ok, L, x, logdet = _factor_and_solve(S)
    assert ok
    assert np.allclose(L, np.linalg.cholesky(S), atol=1e-12)
    assert np.allclose(x, np.linalg.solve(S, np.ones(n)), rtol=1e-9, atol=1e-9)
    assert logdet == pytest.approx(np.linalg.slogdet(S)[1], abs=1e-10)


def test_cholesky_refuses_indefinite_and_nan():
    assert not _factor_and_solve(np.diag([1.0, -1.0, 2.0]))[0]
    assert not _factor_and_solve(np.array([[np.nan]]))[0]


@pytest.mark.parametrize("in_place", [False, True])
@pytest.mark.parametrize("n, m", [(3, 4), (6, 4), (7, 4), (2, 1)])
def test_factored_update_is_the_textbook_kalman_update(rng, n, m, in_place):
    """x⁻ + Kν and the Joseph form with the optimal gain K = P⁻Hᵀ S⁻¹, and νᵀS⁻¹ν."""
    A = rng.normal(size=(n, n))
    Pp = A @ A.T + 0.1 * np.eye(n)
    H = rng.normal(size=(m, n))
    R = rng.uniform(0.1, 1.0, m)
    xp, nu = rng.normal(size=n), rng.normal(size=m)
    S = H @ Pp @ H.T + np.diag(R)
    K = Pp @ H.T @ np.linalg.inv(S)
    IKH = np.eye(n) - K @ H
    maha, x, P = _update(np.linalg.cholesky(S), Pp @ H.T, nu.copy(), xp.copy(), Pp.copy(), in_place)
    assert maha == pytest.approx(nu @ np.linalg.solve(S, nu), rel=1e-10)
    assert np.allclose(x, xp + K @ nu, rtol=1e-10, atol=1e-12)
    assert np.allclose(P, IKH @ Pp @ IKH.T + K @ np.diag(R) @ K.T, rtol=1e-9, atol=1e-12)
    assert np.array_equal(P, P.T)


def test_factored_update_refuses_a_posterior_that_is_not_positive():
    """P⁻Hᵀ inconsistent with P⁻ (a corrupted state): the subtraction would leave a negative variance."""
    Pp = np.diag([1e-6, 1.0])
    PHt = np.array([[1.0], [0.0]])
    maha, x, P = _update(np.array([[1.0]]), PHt, np.array([0.5]), np.zeros(2), Pp, False)
    assert maha == -1.0 and np.all(np.isnan(x)) and np.all(np.isnan(P))


@numba.njit(cache=True)
def _three(A, B, w):
    P, inv_t, R = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    la.matmul3(A, B, P)
    la.inverse_transpose3(A, inv_t)
    la.rotate_increment(B, w, R)
    return P, la.det3(A), inv_t, la.frobenius3(A), R


def test_three_by_three_primitives_against_numpy():
    from ivc import rotations

    rng = np.random.default_rng(4)
    for _ in range(20):
        A = rng.normal(size=(3, 3))
        q = rng.normal(size=4)
        B = rotations.to_matrix(q / np.linalg.norm(q))
        w = rng.normal(size=3) * rng.choice([1e-14, 1e-3, 1.0])
        P, det, inv_t, fro, R = _three(A, B, w)
        np.testing.assert_allclose(P, A @ B, rtol=0, atol=1e-14)
        np.testing.assert_allclose(det, np.linalg.det(A), rtol=1e-12)
        np.testing.assert_allclose(inv_t, np.linalg.inv(A).T, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(fro, np.linalg.norm(A), rtol=1e-14)
        np.testing.assert_allclose(R, B @ rotations.to_matrix(rotations.from_rotvec(w)), rtol=0, atol=1e-14)
