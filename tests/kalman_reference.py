"""Reference discrete Kalman and extended Kalman filters in the Welch & Bishop form (Welch & Bishop 2001, §4).

Test code: the textbook filter against which Welch & Bishop 2001's worked example is checked
(tests/test_predict_kalman.py); the product's filters live in ivc/predict.

The attribute surface follows FilterPy's (``x``, ``P``, ``F``, ``Q``, ``R``, ``H``, ``B``) so
that code written against it reads the same, without depending on it. ``F`` is Welch & Bishop 2001's
``A``. Conventions: ``u_k`` is the control applied over ``(t_{k−1}, t_k]`` and ``Q`` the
process covariance over the same interval (docs/math.md §10 on eq. 4.1 and 4.28).

The covariance update is the Joseph form ``(I − KH) P⁻ (I − KH)ᵀ + K R Kᵀ``, symmetrised,
which stays positive definite under any gain; ``joseph=False`` gives Welch & Bishop 2001's short form
``(I − KH) P⁻`` (eq. 4.13), which reproduces the paper's numbers exactly.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ivc.errors import InputError


class KalmanFilter:
    """Linear KF: ``x_k = F x_{k−1} + B u_k + w``, ``z_k = H x_k + v``, ``w ~ N(0, Q)``, ``v ~ N(0, R)``.

    ``dim_x`` states, ``dim_z`` measurements, ``dim_u`` controls. After :meth:`update`, ``K``,
    ``y`` (innovation) and ``S`` (innovation covariance) hold that step's values;
    ``x_prior``/``P_prior`` and ``x_post``/``P_post`` the estimates either side of it.
    """

    def __init__(self, dim_x: int, dim_z: int, dim_u: int = 0, joseph: bool = True):
        if dim_x < 1 or dim_z < 1 or dim_u < 0:
            raise InputError(f"need dim_x >= 1, dim_z >= 1, dim_u >= 0; got {dim_x}, {dim_z}, {dim_u}")
        self.dim_x, self.dim_z, self.dim_u = dim_x, dim_z, dim_u
        self.x = np.zeros(dim_x)
        self.P = np.eye(dim_x)
        self.F = np.eye(dim_x)
        self.Q = np.eye(dim_x)
        self.H = np.zeros((dim_z, dim_x))
        self.R = np.eye(dim_z)
        self.B = np.zeros((dim_x, dim_u)) if dim_u else None
        self.joseph = joseph
        self.K = np.zeros((dim_x, dim_z))
        self.y = np.zeros(dim_z)
        self.S = np.zeros((dim_z, dim_z))
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()
        self.x_post, self.P_post = self.x.copy(), self.P.copy()

    def predict(self, u: np.ndarray | None = None) -> None:
        """Time update (Table 4.1): ``x⁻ = F x + B u``, ``P⁻ = F P Fᵀ + Q``."""
        self.x = self.F @ self.x
        if u is not None:
            if self.B is None:
                raise InputError("a control input needs dim_u > 0 and B")
            self.x = self.x + self.B @ np.asarray(u, float)
        self.P = self.F @ self.P @ self.F.T + self.Q
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()

    def update(self, z: np.ndarray) -> None:
        """Measurement update (Table 4.2), with a linear solve for the gain (never an inverse)."""
        self._correct(np.atleast_1d(np.asarray(z, float)) - self.H @ self.x, self.H, self.R)

    def _correct(self, innovation: np.ndarray, H: np.ndarray, R: np.ndarray) -> None:
        if not np.all(np.isfinite(innovation)):
            raise InputError(f"non-finite measurement or prediction: innovation {innovation}")
        PHt = self.P @ H.T
        S = H @ PHt + R
        K = np.linalg.solve(S.T, PHt.T).T  # K = P Hᵀ S⁻¹ (S symmetric)
        self.x = self.x + K @ innovation
        I_KH = np.eye(self.dim_x) - K @ H
        if self.joseph:
            P = I_KH @ self.P @ I_KH.T + K @ R @ K.T
            self.P = 0.5 * (P + P.T)
        else:
            self.P = I_KH @ self.P
        self.K, self.y, self.S = K, innovation, S
        self.x_post, self.P_post = self.x.copy(), self.P.copy()


class ExtendedKalmanFilter(KalmanFilter):
    """EKF (Tables 4.3-4.4): nonlinear ``f`` and ``h`` with their Jacobians recomputed every step.

    ``predict(fx, F_jacobian, u)``: ``x⁻ = f(x, u)``, ``P⁻ = A P Aᵀ + W Q Wᵀ`` with ``A = ∂f/∂x``
    (``W`` = ``self.W``, identity by default). ``update(z, hx, H_jacobian)``:
    ``K = P⁻ Hᵀ (H P⁻ Hᵀ + V R Vᵀ)⁻¹``, ``x = x⁻ + K (z − h(x⁻))`` (``V`` = ``self.V``).
    """

    def __init__(self, dim_x: int, dim_z: int, dim_u: int = 0, joseph: bool = True):
        super().__init__(dim_x, dim_z, dim_u, joseph)
        self.W = np.eye(dim_x)
        self.V = np.eye(dim_z)

    def predict(self, fx: Callable | None = None, F_jacobian: Callable | None = None,  # noqa: N803 - FilterPy's names
                u: np.ndarray | None = None) -> None:
        if fx is None:  # the linear model F, B
            super().predict(u)
            return
        A = F_jacobian(self.x, u) if F_jacobian is not None else self.F
        self.F = A
        self.x = np.asarray(fx(self.x, u), float)
        self.P = A @ self.P @ A.T + self.W @ self.Q @ self.W.T
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()

    def update(self, z: np.ndarray, hx: Callable | None = None, H_jacobian: Callable | None = None) -> None:  # noqa: N803
        if hx is None:
            super().update(z)
            return
        H = H_jacobian(self.x) if H_jacobian is not None else self.H
        self.H = H
        innovation = np.atleast_1d(np.asarray(z, float)) - np.atleast_1d(hx(self.x))
        self._correct(innovation, H, self.V @ self.R @ self.V.T)
