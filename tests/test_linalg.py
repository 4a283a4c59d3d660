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
def _inverse(S):
    n = S.shape[0]
    L = np.full((n, n), 7.0)  # stale values in the upper triangle, as a caller's scratch holds
    ok = la.cholesky(S, n, L)
    if ok:
        la.cholesky_inverse(L, n)
    return ok, L


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


@pytest.mark.parametrize("n", [1, 2, 6, 7])
def test_cholesky_inverse_matches_numpy(rng, n):
    A = rng.normal(size=(n, n)) * np.logspace(-3, 1, n)  # columns apart in scale, as a pose's information is
    S = A @ A.T + 1e-6 * np.eye(n)
    ok, inverse = _inverse(S)
    assert ok
    assert np.array_equal(inverse, inverse.T)
    reference = np.linalg.inv(S)
    assert np.linalg.norm(inverse - reference) <= 1e-13 * np.linalg.cond(S) * np.linalg.norm(reference)
    assert not _inverse(S - 2 * np.linalg.eigvalsh(S)[0] * np.eye(n))[0]  # indefinite: refused


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


@numba.njit(cache=True, error_model="numpy")
def _eigenvectors(B):
    out = np.empty((B.shape[0], 3))
    for n in range(B.shape[0]):
        la.principal_eigenvector(B[n], out[n])
    return out


@numba.njit(cache=True, error_model="numpy")
def _squared_twelve_times(B):
    """The plain form of principal_eigenvector: twelve full 3 x 3 squarings, each divided by its trace, then
    the column of largest norm and two power steps."""
    out = np.empty((B.shape[0], 3))
    A, P = np.empty((3, 3)), np.empty((3, 3))
    for n in range(B.shape[0]):
        tr = B[n, 0, 0] + B[n, 1, 1] + B[n, 2, 2]
        for i in range(3):
            for j in range(3):
                A[i, j] = B[n, i, j] / tr
        for _ in range(12):
            la.matmul3(A, A, P)
            t = P[0, 0] + P[1, 1] + P[2, 2]
            for i in range(3):
                for j in range(3):
                    A[i, j] = P[i, j] / t
        best, best_norm = 0, -1.0
        for j in range(3):
            norm = A[0, j] ** 2 + A[1, j] ** 2 + A[2, j] ** 2
            if norm > best_norm:
                best, best_norm = j, norm
        v = out[n]
        for i in range(3):
            v[i] = A[i, best]
        for _ in range(2):
            w0 = B[n, 0, 0] * v[0] + B[n, 0, 1] * v[1] + B[n, 0, 2] * v[2]
            w1 = B[n, 1, 0] * v[0] + B[n, 1, 1] * v[1] + B[n, 1, 2] * v[2]
            w2 = B[n, 2, 0] * v[0] + B[n, 2, 1] * v[1] + B[n, 2, 2] * v[2]
            norm = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            v[0], v[1], v[2] = w0 / norm, w1 / norm, w2 / norm
    return out


def test_principal_eigenvector_is_the_plain_squaring_to_the_bit_and_an_eigenvector(rng):
    """The six-register squaring that stops once the squarings repeat (period 1 or 2) gives the very numbers of
    twelve full squarings, on dipole fields (eigenvalue ratio 1/4), strongly distorted ones and near-degenerate
    ones; and it is the top eigenvector."""
    from ivc import dipole

    r = rng.normal(size=(400, 3))
    r *= rng.uniform(0.1, 1.0, (400, 1)) / np.linalg.norm(r, axis=1, keepdims=True)
    F = dipole.field(r) + rng.normal(size=(400, 3, 3)) * rng.choice([0.0, 0.3, 3.0], (400, 1, 1)) * \
        np.abs(dipole.field(r)).max(axis=(1, 2), keepdims=True)
    B = np.einsum("nai,naj->nij", F, F)  # exactly symmetric, as closed_form_position forms it
    near = rng.normal(size=(50, 3, 3))
    near = np.einsum("nai,naj->nij", near, near) + 40 * np.eye(3)  # eigenvalues close together
    B = np.concatenate([B, (near + near.transpose(0, 2, 1)) / 2])
    v = _eigenvectors(B)
    assert np.array_equal(v, _squared_twelve_times(B))
    values, vectors = np.linalg.eigh(B)
    top = vectors[:, :, -1]
    separated = values[:, -1] > 1.5 * values[:, -2]
    assert separated.sum() > 350
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", v, top))[separated], 1.0, atol=1e-12)
