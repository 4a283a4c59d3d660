"""The small compiled linear-algebra kernels (ivc._linalg) against NumPy."""

import numba
import numpy as np
import pytest

from ivc import _linalg as la


@numba.njit(cache=True)
def _factor_and_invert(S):
    n = S.shape[0]
    L = np.zeros((n, n))
    ok = la.cholesky(S, n, L)
    inv = np.zeros((n, n))
    x = np.zeros(n)
    if ok:
        la.cholesky_inverse(L, n, inv)
        la.cholesky_solve(L, n, np.ones(n), x)
    return ok, L, inv, x, la.cholesky_logdet(L, n) if ok else 0.0


@numba.njit(cache=True)
def _joseph(IKH, Pp, K, R, ncols):
    n, m = K.shape
    T, P = np.zeros((n, n)), np.zeros((n, n))
    la.joseph(IKH, Pp, K, R, n, m, T, P, ncols)
    return P


@pytest.mark.parametrize("n", [1, 3, 4, 6, 7])
def test_cholesky_inverse_solve_and_logdet_match_numpy(rng, n):
    A = rng.normal(size=(n, n))
    S = A @ A.T + 0.1 * np.eye(n)
    ok, L, inv, x, logdet = _factor_and_invert(S)
    assert ok
    assert np.allclose(L, np.linalg.cholesky(S), atol=1e-12)
    assert np.allclose(inv, np.linalg.inv(S), rtol=1e-9, atol=1e-9)
    assert np.array_equal(inv, inv.T)
    assert np.allclose(x, np.linalg.solve(S, np.ones(n)), rtol=1e-9, atol=1e-9)
    assert logdet == pytest.approx(np.linalg.slogdet(S)[1], abs=1e-10)


def test_cholesky_refuses_indefinite_and_nan():
    assert not _factor_and_invert(np.diag([1.0, -1.0, 2.0]))[0]
    assert not _factor_and_invert(np.array([[np.nan]]))[0]


@pytest.mark.parametrize("ncols", [6, 3])
def test_joseph_matches_the_textbook_form(rng, ncols):
    """With H zero from column ncols on, the columns of I − KH there are I's: not read, and skipped exactly."""
    n, m = 6, 4
    A = rng.normal(size=(n, n))
    Pp = A @ A.T
    K = rng.normal(size=(n, m))
    H = rng.normal(size=(m, n))
    H[:, ncols:] = 0.0
    R = rng.uniform(0.1, 1.0, m)
    IKH = np.eye(n) - K @ H
    expected = IKH @ Pp @ IKH.T + K @ np.diag(R) @ K.T
    given = IKH.copy()
    given[:, ncols:] = np.nan  # the identity columns must not be read
    assert np.allclose(_joseph(given, Pp, K, R, ncols), expected, rtol=1e-12, atol=1e-12)
