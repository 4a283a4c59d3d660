"""What a pose-only tracker reports: its solver applied to the measured signal, with Jacobians.

A tracker measures ``S = Tᵀ F(r)`` with ``F = f_D + G`` (docs/math.md §1) and reports the pose
its own solver finds. Two solvers are modelled:

``closed-form`` (default, ivc's own, docs/math.md §3)
    range from ``tr SᵀS``, direction from the principal eigenvector of ``SᵀS``, orientation the
    orthogonal Procrustes rotation ``polar(f_D(r') Sᵀ)``.
``least-squares``
    the pose ``(r', T')`` minimising ``‖T'ᵀ f_D(r') − S‖_F``, started from the closed form.

Both are *rotation-equivariant*: turning the sensor by ``T`` turns the reported orientation by
the same ``T`` and leaves the reported position alone. So at a true position ``r`` the tracker
reports ``r' = φ(r)`` and ``T' = C(r) T``, where ``(φ(r), C(r))`` is the solver's answer for
``S = F(r)`` (a sensor aligned with the source). :func:`distortion` returns that pair.

Jacobians: :func:`reported_pose_jacobian` gives ``∂(r', ω')/∂S`` (6, 9), with the orientation
perturbed on the left, ``T'(S + dS) = exp([ω']×) T'(S)``, and the columns the entries of ``S``
row by row. For the closed form it follows from first-order eigenvector and polar-factor
perturbation; for least squares from the implicit-function theorem on the stationarity of the
cost, with its exact Hessian (second derivatives of ``f_D`` included).

Positions in metres in the source frame; rotations as (..., 3, 3) matrices whose columns are
the sensor axes.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ivc import rotations
from ivc.dipole.field import field, field_jacobian
from ivc.dipole.pose import closed_form_pose, hemisphere_vector
from ivc.errors import InputError
from ivc.pose.solver import dipole_plus, solve_pose

FloatArray = NDArray[np.float64]

SOLVERS = ("closed-form", "least-squares")
#: the least-squares solve stops when its position step is below this (m)
LS_TOLERANCE = 1e-13
LS_CHUNK = 20_000

_SKEW = np.array(  # [e_a]× for a = x, y, z
    [[[0, 0, 0], [0, 0, -1], [0, 1, 0]], [[0, 0, 1], [0, 0, 0], [-1, 0, 0]], [[0, -1, 0], [1, 0, 0], [0, 0, 0]]],
    dtype=float,
)
_BASIS = np.eye(9).reshape(9, 3, 3)  # dS directions, row-major entries of S


def check_solver(solver: str) -> str:
    """``solver`` if it is a known tracker solver, else an :class:`InputError` naming the choices."""
    if solver not in SOLVERS:
        raise InputError(f"unknown tracker solver {solver!r}; use one of {', '.join(SOLVERS)}")
    return solver


def _vee(A: np.ndarray) -> np.ndarray:
    """Axial vector of the skew part's doubled form: vee(A) with [vee(A)]× = A for skew A."""
    return np.stack([A[..., 2, 1], A[..., 0, 2], A[..., 1, 0]], axis=-1)


def field_hessian(r: ArrayLike) -> FloatArray:
    """Second derivatives of ``f_D``: ``H[..., i, j, k, l] = ∂²f_D[i, j] / ∂r_k ∂r_l`` (1/m⁵)."""
    r = np.asarray(r, float)
    rho2 = np.einsum("...i,...i->...", r, r)[..., None, None, None, None]
    d = np.eye(3)
    term0 = (np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d) + np.einsum("ij,kl->ijkl", d, d))
    a = (np.einsum("ik,...j,...l->...ijkl", d, r, r) + np.einsum("jk,...i,...l->...ijkl", d, r, r)
         + np.einsum("ij,...k,...l->...ijkl", d, r, r) + np.einsum("il,...j,...k->...ijkl", d, r, r)
         + np.einsum("jl,...i,...k->...ijkl", d, r, r) + np.einsum("kl,...i,...j->...ijkl", d, r, r))
    quartic = np.einsum("...i,...j,...k,...l->...ijkl", r, r, r, r)
    return 3.0 * term0 / rho2**2.5 - 15.0 * a / rho2**3.5 + 105.0 * quartic / rho2**4.5


def _least_squares(S: np.ndarray, hemisphere: str) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares pose of each finite S (n, 3, 3), from the closed form, in chunks."""
    r0, _ = closed_form_pose(S, hemisphere)
    r, T = np.empty_like(r0), np.empty_like(S)
    model = dipole_plus(None)
    for start in range(0, len(S), LS_CHUNK):
        part = slice(start, start + LS_CHUNK)
        solution = solve_pose(S[part], model, r0[part], step_tolerance=LS_TOLERANCE, max_iterations=100)
        r[part], T[part] = _polish(S[part], solution.position, solution.rotation)
    return r, T


def _polish(S: np.ndarray, r: np.ndarray, T: np.ndarray, steps: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Newton steps with the exact Hessian on ``‖S − T'ᵀ f_D(r')‖²``: from Levenberg-Marquardt's answer
    to the minimum at machine precision (so the reported pose is a smooth function of S)."""
    for _ in range(steps):
        J, e, H = _least_squares_terms(S, r, T)
        with np.errstate(invalid="ignore"):
            step = np.linalg.solve(H, np.einsum("nki,nk->ni", J, e)[..., None])[..., 0]
        good = np.all(np.isfinite(step), axis=1)
        step[~good] = 0.0
        r = r + step[:, :3]
        T = rotations.to_matrix(rotations.from_rotvec(step[:, 3:])) @ T
    return r, T


def reported_pose(S: ArrayLike, solver: str = "closed-form", hemisphere: str = "+x"
                  ) -> tuple[FloatArray, FloatArray]:
    """The pose ``(position (..., 3) m, rotation (..., 3, 3))`` a tracker with ``solver`` reports for
    signal matrices ``S`` (..., 3, 3). Non-finite matrices give NaN."""
    check_solver(solver)
    hemisphere_vector(hemisphere)
    S = np.asarray(S, float)
    if S.shape[-2:] != (3, 3):
        raise InputError(f"signal matrices must have shape (..., 3, 3), got {S.shape}")
    lead = S.shape[:-2]
    flat = S.reshape(-1, 3, 3)
    usable = np.all(np.isfinite(flat.reshape(-1, 9)), axis=1) & (np.einsum("nij,nij->n", flat, flat) > 0)
    r, T = np.full((len(flat), 3), np.nan), np.full((len(flat), 3, 3), np.nan)
    if usable.all():
        r, T = (closed_form_pose if solver == "closed-form" else _least_squares)(flat, hemisphere)
    elif usable.any():
        r[usable], T[usable] = (closed_form_pose if solver == "closed-form" else _least_squares)(flat[usable],
                                                                                                 hemisphere)
    return r.reshape(*lead, 3), T.reshape(*lead, 3, 3)


def _closed_form_jacobian(S: np.ndarray, r: np.ndarray, T: np.ndarray) -> np.ndarray:
    """∂(r', ω')/∂S (n, 6, 9) of the closed form at its solution (r, T)."""
    B = np.swapaxes(S, -1, -2) @ S
    dB = np.einsum("nki,dkj->ndij", S, _BASIS)
    dB = dB + np.swapaxes(dB, -1, -2)  # dSᵀS + SᵀdS
    tau = np.trace(B, axis1=-2, axis2=-1)
    rng = np.linalg.norm(r, axis=-1)
    v = r / rng[:, None]  # the eigenvector, with the hemisphere's sign
    lam, V = np.linalg.eigh(B)
    d_tau = np.trace(dB, axis1=-2, axis2=-1)  # (n, 9)
    d_range = -rng[:, None] / (6 * tau[:, None]) * d_tau
    dBv = np.einsum("ndij,nj->ndi", dB, v)
    dv = np.zeros((len(S), 9, 3))
    for k in (0, 1):
        Vk = V[:, :, k]
        gap = lam[:, 2] - lam[:, k]
        dv += (np.einsum("ni,ndi->nd", Vk, dBv) / gap[:, None])[..., None] * Vk[:, None, :]
    dr = d_range[..., None] * v[:, None, :] + rng[:, None, None] * dv  # (n, 9, 3)
    # polar factor of K = f_D(r) Sᵀ: T = K P⁻¹
    fd, dfd = field(r), field_jacobian(r)
    K = fd @ np.swapaxes(S, -1, -2)
    P = np.swapaxes(T, -1, -2) @ K
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    dK = np.einsum("nijk,ndk,nlj->ndil", dfd, dr, S) + np.einsum("nij,dlj->ndil", fd, _BASIS)
    UtdK = np.einsum("nji,ndjk->ndik", T, dK)
    rhs = _vee(UtdK - np.swapaxes(UtdK, -1, -2))  # (n, 9, 3)
    A = np.trace(P, axis1=-2, axis2=-1)[:, None, None] * np.eye(3) - P
    w = np.linalg.solve(A[:, None], rhs[..., None])[..., 0]  # right perturbation of T
    omega = np.einsum("nij,ndj->ndi", T, w)  # as a left perturbation
    return np.concatenate([dr, omega], axis=-1).swapaxes(-1, -2)


def _least_squares_terms(S: np.ndarray, r: np.ndarray, T: np.ndarray):
    """At pose (r, T): ``J = ∂P/∂x`` (n, 9, 6), the residual ``e = S − P`` (n, 9) and the exact Hessian
    ``H = JᵀJ − Σ e_k ∂²P_k/∂x²`` (n, 6, 6) of ``½‖S − P‖²``, with ``P(x) = T'ᵀ f_D(r')`` and
    ``x = (r', θ)``, θ the left rotation increment of T'."""
    fd, dfd, hfd = field(r), field_jacobian(r), field_hessian(r)
    Tt = np.swapaxes(T, -1, -2)
    # P(r', θ) = Tᵀ exp(−[θ]×) f_D(r'), left perturbation θ of T'
    P_r = np.einsum("nai,najk->nijk", T, dfd)  # ∂P/∂r_k (n, 3, 3, 3)
    P_w = -np.einsum("nia,bac,ncj->nijb", Tt, _SKEW, fd)  # ∂P/∂θ_b
    J = np.concatenate([P_r, P_w], axis=-1).reshape(len(S), 9, 6)
    e = (S - Tt @ fd).reshape(len(S), 9)  # residual S − P
    P_rr = np.einsum("nai,najkl->nijkl", T, hfd)
    P_wr = -np.einsum("nia,bac,ncjk->nijbk", Tt, _SKEW, dfd)
    sym = 0.5 * (np.einsum("acd,bde->abce", _SKEW, _SKEW) + np.einsum("bcd,ade->abce", _SKEW, _SKEW))
    P_ww = np.einsum("nia,bcad,ndj->nijbc", Tt, sym, fd)
    second = np.zeros((len(S), 3, 3, 6, 6))
    second[..., :3, :3] = P_rr
    second[..., 3:, :3] = P_wr
    second[..., :3, 3:] = np.swapaxes(P_wr, -1, -2)
    second[..., 3:, 3:] = P_ww
    H = np.einsum("nki,nkj->nij", J, J) - np.einsum("nk,nkab->nab", e, second.reshape(len(S), 9, 6, 6))
    return J, e, H


def _least_squares_jacobian(S: np.ndarray, r: np.ndarray, T: np.ndarray) -> np.ndarray:
    """∂(r', ω')/∂S (n, 6, 9) of the least-squares pose at its solution (r, T), by the implicit-function
    theorem on the stationarity ``Jᵀe = 0``: ``dx = H⁻¹ Jᵀ dS`` (see :func:`_least_squares_terms`)."""
    J, _, H = _least_squares_terms(S, r, T)
    return np.linalg.solve(H, np.swapaxes(J, -1, -2))


def reported_pose_jacobian(S: ArrayLike, solver: str = "closed-form", hemisphere: str = "+x"
                           ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`reported_pose` and its Jacobian ``∂(r', ω')/∂S`` (..., 6, 9): rows the position (m) and
    the left rotation increment (rad), columns the entries of S row by row."""
    r, T = reported_pose(S, solver, hemisphere)
    S = np.asarray(S, float)
    lead = S.shape[:-2]
    flat, rf, Tf = S.reshape(-1, 3, 3), r.reshape(-1, 3), T.reshape(-1, 3, 3)
    J = np.full((len(flat), 6, 9), np.nan)
    ok = np.all(np.isfinite(rf), axis=1) & np.all(np.isfinite(flat.reshape(-1, 9)), axis=1)
    if ok.any():
        jac = _closed_form_jacobian if solver == "closed-form" else _least_squares_jacobian
        with np.errstate(invalid="ignore", divide="ignore"):
            J[ok] = jac(flat[ok], rf[ok], Tf[ok])
    return r, T, J.reshape(*lead, 6, 9)


def distortion(r: ArrayLike, g: ArrayLike | None = None, dg: ArrayLike | None = None,
               solver: str = "closed-form", hemisphere: str = "+x", jacobian: bool = False):
    """The pose-domain distortion at true positions r (..., 3) m, with secondary field ``g`` (..., 3, 3).

    Returns ``(φ(r) (..., 3), C(r) (..., 3, 3))``: a sensor at ``(r, T)`` is reported at
    ``(φ(r), C(r) T)``. With ``jacobian=True`` also ``∂φ/∂r`` (..., 3, 3) and ``∂ω/∂r`` (..., 3, 3)
    (left rotation increment of C per metre), which need ``dg = ∂g/∂r`` (..., 3, 3, 3) when ``g`` is given;
    and ``∂(φ, ω)/∂G`` (..., 6, 9), the Jacobian with respect to the secondary field's entries.
    """
    r = np.asarray(r, float)
    F = field(r) if g is None else field(r) + np.asarray(g, float)
    if not jacobian:
        return reported_pose(F, solver, hemisphere)
    position, turn, J = reported_pose_jacobian(F, solver, hemisphere)
    dF = field_jacobian(r)
    if g is not None:
        if dg is None:
            raise InputError("distortion(jacobian=True) with a secondary field needs its Jacobian dg")
        dF = dF + np.asarray(dg, float)
    dF = dF.reshape(*r.shape[:-1], 9, 3)
    d = J @ dF
    return position, turn, d[..., :3, :], d[..., 3:, :], J


def left_difference(A: ArrayLike, B: ArrayLike) -> FloatArray:
    """Rotation vector (..., 3) rad of ``A Bᵀ``: the left increment that turns B into A."""
    return rotations.to_rotvec(rotations.from_matrix(np.asarray(A, float) @ np.swapaxes(np.asarray(B, float), -1, -2)))
