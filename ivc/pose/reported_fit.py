"""Fit a harmonic secondary field to (true pose, reported pose) pairs, through the tracker model.

For pose-only trackers the data are pairs: a sensor's true pose ``(r, T)`` (declared, or carried
by the wand from sensor 0) and the pose the tracker reported, ``(v, Q)``. The tracker model
(:mod:`ivc.pose.tracker_solver`) says ``v = φ(r)`` and ``Q = C(r) T``, with ``(φ, C)`` the
tracker solver applied to ``f_D(r) + G(r)``. Here ``G`` is a sum of gradients of harmonic
potentials, ``G(r) = Σ_k b_k(r) c_kᵀ`` (each source column a curl- and divergence-free field, as
in the signal path, docs/lut.md), and the coefficients ``c`` (K, 3) are fitted by Gauss-Newton on
the six pose residuals of every pair,

    e = [v − φ(r),  L · rotvec(Q Tᵀ C(r)ᵀ)]

(metres; the orientation residual, in radians, counts as ``L`` metres per radian). Each
iteration linearises the reported pose in ``G`` with the solver's exact Jacobian and solves
for the coefficients themselves (not an increment), so that every degree's solution is a
prefix solve of the same normal equations and K-fold cross-validation chooses the degree
for the cost of one pass, as :mod:`ivc.lut.fit_harmonic` does for signals. The distortion
is large (tens of millimetres, hundreds of milliradians next to metal), so the steps are damped
(Levenberg-Marquardt, towards the current coefficients) and a step is kept only if it lowers
the residual.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.linalg.blas import dsyrk

from ivc import dipole
from ivc.errors import InputError
from ivc.pose.tracker_solver import check_solver, left_difference, reported_pose_jacobian

#: metres of position that one radian of orientation residual counts as (about the ratio of the
#: tracker's position to orientation noise at half a metre: 0.03 mm against 0.1 mrad)
ORIENTATION_LENGTH = 0.3
CHUNK = 5_000
#: each residual row's weight in the design matrix: the orientation rows' Jacobian counts L metres per radian
ROW_WEIGHT = np.array([1.0, 1.0, 1.0, ORIENTATION_LENGTH, ORIENTATION_LENGTH, ORIENTATION_LENGTH])
GAUSS_NEWTON_ITERATIONS = 30
#: the fit stops when an iteration lowers the RMS pose residual by less than this (m) plus RELATIVE_TOLERANCE of it
TOLERANCE = 1e-9
INITIAL_DAMPING = 1e-3
RELATIVE_TOLERANCE = 1e-3
RIDGE = 1e-12
#: the warm start's share of the pairs (every COARSE_STRIDE-th), used where it has at least COARSE_ROWS residual rows
#: per coefficient
COARSE_STRIDE, COARSE_ROWS = 8, 20

Basis = Callable[[np.ndarray], np.ndarray]  # positions (n, 3) -> gradients (n, K, 3)


@dataclass
class PosePairs:
    """``position`` (N, 3) m and ``rotation`` (N, 3, 3): true poses; ``reported_position`` (N, 3) m and
    ``reported_rotation`` (N, 3, 3): what the tracker reported there; ``frame``, ``sensor`` (N,) int."""

    position: np.ndarray
    rotation: np.ndarray
    reported_position: np.ndarray
    reported_rotation: np.ndarray
    frame: np.ndarray
    sensor: np.ndarray

    def __post_init__(self):
        n = len(self.position)
        shapes = [(self.position, (n, 3)), (self.rotation, (n, 3, 3)), (self.reported_position, (n, 3)),
                  (self.reported_rotation, (n, 3, 3)), (self.frame, (n,)), (self.sensor, (n,))]
        if any(a.shape != s for a, s in shapes):
            raise InputError("pose pairs: inconsistent array shapes")
        finite = [np.all(np.isfinite(a)) for a, _ in shapes[:4]]
        if not all(finite):
            raise InputError("pose pairs must be finite; drop the gated-out samples first")

    def __len__(self) -> int:
        return len(self.position)

    @property
    def observed_turn(self) -> np.ndarray:
        """``C`` the pairs say the tracker applied: ``Q Tᵀ`` (N, 3, 3)."""
        return self.reported_rotation @ np.swapaxes(self.rotation, -1, -2)

    def subset(self, mask) -> PosePairs:
        return PosePairs(self.position[mask], self.rotation[mask], self.reported_position[mask],
                         self.reported_rotation[mask], self.frame[mask], self.sensor[mask])

    def folds(self, k: int = 5, block_frames: int = 500) -> np.ndarray:
        """Cross-validation fold of each pair: blocks of consecutive frames dealt round-robin."""
        return (self.frame // block_frames) % k


def pose_residuals(pairs: PosePairs, position: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """``[v − φ, L · rotvec(C_observed C_modelᵀ)]`` (N, 6): metres, the orientation as metres via L."""
    return np.concatenate([pairs.reported_position - position,
                           ORIENTATION_LENGTH * left_difference(pairs.observed_turn, turn)], axis=1)


def predicted(pairs_position: np.ndarray, basis: Basis, coefficients: np.ndarray, solver: str, hemisphere: str):
    """Reported poses the model predicts at true positions (n, 3): (φ, C, ∂(φ, ω)/∂G (n, 6, 9), basis)."""
    b = basis(pairs_position)
    G = np.swapaxes(b, 1, 2) @ coefficients
    position, turn, J = reported_pose_jacobian(dipole.field(pairs_position) + G, solver, hemisphere)
    return position, turn, J, b


def design(J: np.ndarray, b: np.ndarray) -> np.ndarray:
    """∂(reported pose)/∂c (n, 6, 3K): the solver's Jacobian in G chained with G's basis, coefficients
    ordered by potential then source column (so a lower degree's block is a prefix)."""
    n, K = b.shape[:2]
    # X[n, a, k, j] = Σ_i b[n, k, i] J[n, a, i, j]: one batched product (K, 3) @ (3, 6·3) per pair
    Jg = J.reshape(n, 6, 3, 3).transpose(0, 2, 1, 3).reshape(n, 3, 18)
    return (b @ Jg).reshape(n, K, 6, 3).transpose(0, 2, 1, 3).reshape(n, 6, 3 * K)


@dataclass
class _Normal:
    gram: np.ndarray  # (k, P, P)
    rhs: np.ndarray  # (k, P)
    yy: np.ndarray  # (k,)
    count: np.ndarray  # (k,)


def _accumulate(pairs: PosePairs, basis: Basis, coefficients: np.ndarray, fold: np.ndarray, folds: int,
                solver: str, hemisphere: str, progress) -> tuple[_Normal, float]:
    """Normal equations for the coefficients themselves, linearised at ``coefficients``; and the RMS
    pose residual (m) there. ``fold``: each pair's fold, in ascending order (so a chunk is one fold's)."""
    P = coefficients.size
    normal = _Normal(np.zeros((folds, P, P)), np.zeros((folds, P)), np.zeros(folds), np.zeros(folds))
    sse = 0.0
    for k in range(folds):
        members = np.flatnonzero(fold == k)
        for start in range(0, len(members), CHUNK):
            part = slice(members[start], members[min(start + CHUNK, len(members)) - 1] + 1)
            sub = pairs.subset(part)
            position, turn, J, b = predicted(sub.position, basis, coefficients, solver, hemisphere)
            e = pose_residuals(sub, position, turn)  # (n, 6)
            X = (design(J, b) * ROW_WEIGHT[None, :, None]).reshape(-1, P)
            y = (e + (X @ coefficients.reshape(-1)).reshape(-1, 6)).reshape(-1)  # the absolute form's target
            sse += float(np.sum(e**2))
            normal.gram[k] += dsyrk(1.0, X.T, trans=0)  # the upper triangle of XᵀX: half a general product's work
            normal.rhs[k] += X.T @ y
            normal.yy[k] += y @ y
            normal.count[k] += len(sub)
            if progress is not None:
                progress(len(sub))
    normal.gram += np.triu(normal.gram, 1).swapaxes(1, 2)  # the lower triangles, once
    return normal, float(np.sqrt(sse / max(len(pairs), 1)))


def _solve(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    scale = np.sqrt(np.maximum(np.diag(gram), 1e-300))
    scaled = gram / np.outer(scale, scale) + RIDGE * np.eye(len(gram))
    return np.linalg.solve(scaled, rhs / scale) / scale


def _cv_scores(normal: _Normal, counts: dict[int, int]) -> dict[int, float]:
    """Held-out RMS pose residual (m) of each degree (3 × counts[degree] leading unknowns)."""
    gram_all, rhs_all = normal.gram.sum(axis=0), normal.rhs.sum(axis=0)
    scores = {}
    for degree, K in counts.items():
        m = 3 * K
        sse = 0.0
        for f in range(len(normal.gram)):
            if normal.count[f] == 0:
                continue
            c = _solve(gram_all[:m, :m] - normal.gram[f, :m, :m], rhs_all[:m] - normal.rhs[f, :m])
            sse += normal.yy[f] - 2 * c @ normal.rhs[f, :m] + c @ normal.gram[f, :m, :m] @ c
        scores[degree] = float(np.sqrt(max(sse, 0.0) / normal.count.sum()))
    return scores


def fit_through_tracker(pairs: PosePairs, basis: Basis, counts: dict[int, int], solver: str = "closed-form",
                        hemisphere: str = "+x", degree: int | None = None, folds: int = 5,
                        iterations: int = GAUSS_NEWTON_ITERATIONS,
                        progress: Callable[[int], None] | None = None,
                        start: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Coefficients (K, 3) of ``G = Σ_k b_k c_kᵀ`` whose tracker model reproduces the reported poses.

    ``basis(r)`` gives the gradients (n, K_max, 3) of the potentials at positions (n, 3); ``counts``
    maps each candidate degree to its number of potentials (a prefix of the basis). ``degree``:
    fixed, or None to choose it by K-fold cross-validation (the lowest within 1% of the best score).
    ``start``: coefficients (k, 3) to start from (a prefix of the basis; default: zero, then the first steps on
    every COARSE_STRIDE-th pair). From zero, a room whose field rivals the source's can stop far from the
    solution (the strong scene's self-calibrated pairs: 6.8 mm RMS from zero, 0.06 mm from the self-calibration's
    coefficients).
    Returns the coefficients, zero-padded to K_max, and a report.
    """
    check_solver(solver)
    if not counts:
        raise InputError("no candidate degree to fit")
    if degree is not None and degree not in counts:
        raise InputError(f"degree {degree} is not among the candidates {sorted(counts)}")
    K_max = max(counts.values())
    top = max(counts) if degree is None else degree
    if len(pairs) * 6 < 3 * counts[top] and degree is not None:
        raise InputError(f"{len(pairs)} pose pairs are too few for {3 * counts[top]} coefficients")
    candidates = {d: k for d, k in counts.items() if d <= top and 6 * len(pairs) >= 3 * k}
    if not candidates:
        raise InputError(f"{len(pairs)} pose pairs are too few for any candidate degree")
    top = max(candidates)
    folds = max(1, min(folds, len(np.unique(pairs.folds(folds))))) if len(pairs) >= 50 else 1
    fold = pairs.folds(folds) if folds > 1 else np.zeros(len(pairs), int)
    order = np.argsort(fold, kind="stable")  # each fold's pairs together, in time order
    coefficients = np.zeros((K_max, 3))
    coarse = pairs.subset(slice(None, None, COARSE_STRIDE))
    if start is not None:
        coefficients[: min(len(start), K_max)] = np.asarray(start, float)[:K_max]
    elif 6 * len(coarse) >= COARSE_ROWS * 3 * candidates[top]:
        # the first steps, from G = 0 to near the solution, on every COARSE_STRIDE-th pair: the full data then
        # needs two or three steps instead of eight or nine (each step is a pass over all pairs)
        start, _ = fit_through_tracker(coarse, basis, {top: candidates[top]}, solver, hemisphere, top, 1, iterations)
        coefficients[: len(start)] = start
    pairs, fold = pairs.subset(order), fold[order]
    history = []
    chosen = top
    scores: dict[int, float] = {}
    damping = INITIAL_DAMPING
    normal, rms = _accumulate(pairs, basis, coefficients, fold, folds, solver, hemisphere, progress)
    history.append(rms)
    for _ in range(iterations):
        if folds > 1:
            scores = _cv_scores(normal, candidates)
            if degree is None:
                best = min(scores.values())
                chosen = min(d for d, s in scores.items() if s <= 1.01 * best)
        m = 3 * candidates[chosen]
        gram, rhs = normal.gram.sum(axis=0)[:m, :m], normal.rhs.sum(axis=0)[:m]
        current = coefficients.reshape(-1)[:m]
        while True:  # Levenberg-Marquardt in the absolute form: damped towards the current coefficients
            diag = damping * np.diag(gram)
            trial = np.zeros(K_max * 3)
            trial[:m] = _solve(gram + np.diag(diag), rhs + diag * current)
            trial = trial.reshape(K_max, 3)
            new_normal, new_rms = _accumulate(pairs, basis, trial, fold, folds, solver, hemisphere, progress)
            if np.isfinite(new_rms) and new_rms <= rms:
                damping = max(damping * 0.1, 1e-9)
                break
            damping *= 10.0
            if damping > 1e6:
                break
        if not (np.isfinite(new_rms) and new_rms <= rms):
            break
        improvement = rms - new_rms
        coefficients, normal, rms = trial, new_normal, new_rms
        history.append(rms)
        if improvement < TOLERANCE + RELATIVE_TOLERANCE * rms:
            break
    report = {"degree": chosen, "degree_chosen_by": "user" if degree is not None else (
        "cross-validation" if folds > 1 else "largest that the data determine"),
              "cv_rms_mm": 1000 * scores[chosen] if scores else None,
              "cv_rms_mm_by_degree": {str(d): 1000 * s for d, s in scores.items()},
              "cv_folds": folds, "pose_rms_mm_by_iteration": [1000 * h for h in history],
              "orientation_length_m": ORIENTATION_LENGTH}
    return coefficients, report
