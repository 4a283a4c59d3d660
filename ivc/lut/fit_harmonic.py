"""The physics-constrained fit: each source column of ``G`` is the gradient of a harmonic potential.

Inside the source-free mapped volume every column of ``G`` is a magnetic field, so it
is ``∇Φ_j`` with ``Φ_j`` harmonic (docs/math.md §8). ``Φ_j`` is expanded in the regular
solid harmonics of degree 1..L about the centre of the data (``ivc.lut.harmonics``):
``(L + 1)² − 1`` coefficients per column, shared basis, weighted least squares.

The degree is chosen by K-fold cross-validation. The folds' normal equations are
accumulated once; the held-out weighted residual of fold ``f`` follows exactly from
them, ``yᵀy_f − 2 cᵀ Xᵀy_f + cᵀ XᵀX_f c``, so all degrees are scored for the cost of
one pass over the data. Outliers are down-weighted by Huber iteratively reweighted
least squares on the pose-equivalent residual.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.linalg.blas import dsyrk
from threadpoolctl import threadpool_limits

from ivc.errors import InputError
from ivc.lut import harmonics
from ivc.lut.cross_validation import BlockedKFold
from ivc.lut.fitter import Fitter, register
from ivc.lut.samples import ERROR_FLOOR, FieldSamples
from ivc.table.grid import Grid

MAX_DEGREE = 10
CHUNK = 20_000
HUBER_K = 3.0
ROBUST_ITERATIONS = 2
#: passes over the data per fit (for progress totals)
PASSES = ROBUST_ITERATIONS + 1
RIDGE = 1e-10  # relative Tikhonov term: keeps high degrees solvable where the data are thin


@dataclass
class HarmonicModel:
    """``G(r) = Σ_k ∇Φ_k((r − centre) / scale) c_k`` with ``coefficients`` (K, 3)."""

    centre: np.ndarray
    scale: float
    degree: int
    coefficients: np.ndarray

    def __call__(self, r: np.ndarray) -> np.ndarray:
        r = np.asarray(r, float)
        flat = r.reshape(-1, 3)
        out = np.empty((len(flat), 3, 3))
        for start in range(0, len(flat), CHUNK):
            rows = harmonics.gradient_rows((flat[start : start + CHUNK] - self.centre) / self.scale, self.degree)
            out[start : start + CHUNK] = (rows.reshape(-1, rows.shape[-1]) @ self.coefficients).reshape(-1, 3, 3)
        return out.reshape(*r.shape[:-1], 3, 3)


@dataclass
class NormalEquations:
    """Per-fold normal equations at the maximum degree: XᵀWX (k, K, K), XᵀWy (k, K, 3), yᵀWy (k,), Σν (k,)."""

    gram: np.ndarray
    rhs: np.ndarray
    yy: np.ndarray
    count: np.ndarray

    def copy(self) -> NormalEquations:
        return NormalEquations(self.gram.copy(), self.rhs.copy(), self.yy.copy(), self.count.copy())


def _add(normal: NormalEquations, f: int, samples: FieldSamples, lever: np.ndarray, part: np.ndarray, rows: np.ndarray,
         weight: np.ndarray, sign: float = 1.0) -> None:
    """Add (``sign`` −1: remove) the weighted rows of samples ``part`` to fold ``f``'s normal equations.

    ``lever``: every sample's leverage λ; ``rows`` (n, 3, K): the basis gradients of those samples,
    overwritten. XᵀX is accumulated by a symmetric rank-k update (BLAS syrk: half the work of a
    general product).
    """
    K = rows.shape[-1]
    root = np.sqrt(weight)
    rows *= root[:, None, None]
    X = rows.reshape(-1, K)  # rows (sample, component)
    Y = (samples.fields[part] * root[:, None, None]).reshape(-1, 3)  # columns: source coil
    upper = dsyrk(sign, X.T, trans=0)  # the upper triangle of sign XᵀX
    normal.gram[f] += upper + np.triu(upper, 1).T
    normal.rhs[f] += sign * (X.T @ Y)
    normal.yy[f] += sign * np.sum(Y**2)
    normal.count[f] += sign * np.sum(weight / lever[part] ** 2)


def _chunks(folds: np.ndarray, k: int):
    """(fold, sample indices) in chunks of at most CHUNK samples."""
    for f in range(k):
        members = np.flatnonzero(folds == f)
        for start in range(0, len(members), CHUNK):
            yield f, members[start : start + CHUNK]


def _rows(samples: FieldSamples, part: np.ndarray, centre, scale, degree, buffer: np.ndarray) -> np.ndarray:
    """Basis gradients (n, 3, K) of samples ``part`` into the front of ``buffer``."""
    out = buffer[: len(part) * 3 * harmonics.count(degree)].reshape(len(part), 3, harmonics.count(degree))
    return harmonics.gradient_rows((samples.positions[part] - centre) / scale, degree, out)


def accumulate_normal(samples, lever, base, folds, k, centre, scale, degree, progress) -> NormalEquations:
    """One pass over the data: the fold normal equations with the weights ``base``."""
    K = harmonics.count(degree)
    normal = NormalEquations(np.zeros((k, K, K)), np.zeros((k, K, 3)), np.zeros(k), np.zeros(k))
    buffer = np.empty(CHUNK * 3 * K)
    for f, part in _chunks(folds, k):
        _add(normal, f, samples, lever, part, _rows(samples, part, centre, scale, degree, buffer), base[part])
        if progress is not None:
            progress(len(part))
    return normal


def reweight_normal(unweighted: NormalEquations, samples, lever, base, folds, k, centre, scale, degree, coefficients,
                    cut, progress) -> tuple[NormalEquations, np.ndarray]:
    """The normal equations with Huber weights, from those with the base weights.

    Each sample's weight is Huber-reduced by its standardised pose-equivalent residual under
    ``coefficients`` (``cut`` in the same units). Only the reduced samples' rows change, so their
    weight reductions are subtracted from ``unweighted`` rather than every sample's rows summed
    again: the same equations for a pass of residuals (the chosen degree) plus the few outliers.
    Returns the equations and the weights.
    """
    chosen = round(np.sqrt(len(coefficients) + 1)) - 1  # the degree of the coefficients
    normal = unweighted.copy()
    weights = base.copy()
    buffer = np.empty(CHUNK * 3 * harmonics.count(degree))
    for f, part in _chunks(folds, k):
        rows = _rows(samples, part, centre, scale, chosen, buffer)
        residual = standardised_residual(samples, lever, part, rows, coefficients)
        factor = np.minimum(1.0, cut / np.maximum(residual, 1e-300))
        reduced = factor < 1.0
        if reduced.any():
            weights[part] *= factor
            outliers = part[reduced]
            _add(normal, f, samples, lever, outliers, _rows(samples, outliers, centre, scale, degree, buffer),
                 base[outliers] * (1.0 - factor[reduced]), sign=-1.0)
        if progress is not None:
            progress(len(part))
    return normal, weights


def standardised_residual(samples, lever, part, rows, coefficients) -> np.ndarray:
    """``λ |G_model − G|_F / σ`` of the samples in ``part``: a residual in units of the sample's error.
    ``rows`` (n, 3, K'): their basis gradients, K' >= len(coefficients)."""
    K = len(coefficients)
    predicted = (np.ascontiguousarray(rows[..., :K]).reshape(-1, K) @ coefficients).reshape(len(part), 3, 3)
    sigma = np.sqrt(samples.error[part] ** 2 + ERROR_FLOOR**2)
    return lever[part] * np.linalg.norm(predicted - samples.fields[part], axis=(1, 2)) / sigma


def solve_normal(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Normal equations with every basis column scaled to unit norm first (solid harmonics of
    high degree are tiny inside the unit ball), plus a small relative ridge."""
    scale = np.sqrt(np.maximum(np.diag(gram), 1e-300))
    scaled = gram / np.outer(scale, scale) + RIDGE * np.eye(len(gram))
    return np.linalg.solve(scaled, rhs / scale[:, None]) / scale[:, None]


def cv_scores(normal: NormalEquations, max_degree: int) -> dict[int, float]:
    """Held-out pose-equivalent RMS (m) for each degree 1..max_degree."""
    gram_all, rhs_all = normal.gram.sum(axis=0), normal.rhs.sum(axis=0)
    scores = {}
    for degree in range(1, max_degree + 1):
        K = harmonics.count(degree)
        sse = 0.0
        for f in range(len(normal.gram)):
            if normal.count[f] == 0:
                continue
            c = solve_normal(gram_all[:K, :K] - normal.gram[f, :K, :K], rhs_all[:K] - normal.rhs[f, :K])
            sse += normal.yy[f] - 2 * np.sum(c * normal.rhs[f, :K]) + np.sum(c * (normal.gram[f, :K, :K] @ c))
        scores[degree] = float(np.sqrt(max(sse, 0.0) / normal.count.sum()))
    return scores


@register
class HarmonicFit(Fitter):
    """The harmonic fit as a :class:`~ivc.lut.fitter.Fitter`.

    ``degree``: the harmonic degree L, or None to choose it by ``cv`` among 1..``max_degree`` (the
    lowest within 1 % of the best held-out score). Fitted attributes: ``model_``
    (:class:`HarmonicModel`), ``degree_``, ``scores_`` (held-out score per degree, m),
    ``cv_score_`` (the chosen degree's, m), ``weights_`` (the final Huber-reduced weights) and
    ``report_``. Its cross-validation is exact and free: the held-out residuals of ``cv``'s folds
    follow from the fold normal equations (with the weights of the whole fit), so
    :meth:`cross_validate` of the samples it was fitted to is ``cv_score_``.
    """

    name = "harmonic"

    def __init__(self, degree: int | None = None, max_degree: int = MAX_DEGREE, cv: BlockedKFold | None = None):
        if degree is not None and (not isinstance(degree, int | np.integer) or degree < 1):
            raise InputError(f"harmonic degree must be a whole number of at least 1, got {degree!r}")
        if not isinstance(max_degree, int | np.integer) or max_degree < 1:
            raise InputError(f"max_degree must be a whole number of at least 1, got {max_degree!r}")
        self.degree = degree
        self.max_degree = max_degree
        self.cv = BlockedKFold() if cv is None else cv

    @property
    def progress_label(self) -> str:
        return f"fitting (harmonic, {PASSES} passes)"

    def progress_units(self, samples: FieldSamples) -> int:
        return len(samples) * PASSES

    def fit(self, samples: FieldSamples, grid: Grid | None = None,
            progress: Callable[[int], None] | None = None) -> HarmonicFit:
        """Fit the samples (``grid`` is not needed). BLAS runs on one thread meanwhile: the fit's dozens of
        small (≤ 120²) solves cost tens of milliseconds each when BLAS threads spin beside the compiled
        basis (0.38 s against 9 ms for one scoring on the 2-core machine), and the rank-k updates lose little.
        """
        with threadpool_limits(limits=1, user_api="blas"):
            model, scores, weights, report = _fit_harmonic(samples, self.degree, self.max_degree,
                                                           self.cv.folds(samples), self.cv.k, progress)
        self.model_, self.degree_, self.scores_, self.weights_ = model, model.degree, scores, weights
        self.cv_score_ = scores[model.degree]
        self.report_ = report
        self._fitted_to = samples
        return self

    def cross_validate(self, samples: FieldSamples, grid: Grid | None = None) -> float:
        """``cv_score_`` for the samples of the fit; other samples are scored by refitting per fold."""
        if getattr(self, "_fitted_to", None) is samples:
            return self.cv_score_
        return super().cross_validate(samples, grid)


def fit_harmonic(samples: FieldSamples, degree: int | None = None, max_degree: int = MAX_DEGREE, folds: int = 5,
                 progress: Callable[[int], None] | None = None) -> tuple[HarmonicModel, dict]:
    """:class:`HarmonicFit` with ``folds`` blocked folds, as a function: the model and the fit report
    (chosen degree, CV score per degree in mm, samples down-weighted as outliers)."""
    fitter = HarmonicFit(degree, max_degree, BlockedKFold(folds)).fit(samples, progress=progress)
    return fitter.model_, fitter.report_


def _fit_harmonic(samples, degree, max_degree, fold, folds, progress):
    if len(samples) < 3 * harmonics.count(2):
        raise InputError(f"{len(samples)} samples are too few for a harmonic fit")
    top = max_degree if degree is None else degree
    centre = 0.5 * (samples.positions.min(axis=0) + samples.positions.max(axis=0))
    scale = float(np.max(np.linalg.norm(samples.positions - centre, axis=1)))
    base = samples.weights()
    lever = samples.leverage()
    probe = np.random.default_rng(0).choice(len(samples), min(len(samples), CHUNK), replace=False)
    unweighted = accumulate_normal(samples, lever, base, fold, folds, centre, scale, top, progress)
    normal, weights = unweighted, base
    for iteration in range(ROBUST_ITERATIONS + 1):
        scores = cv_scores(normal, top)
        chosen = top
        if degree is None:
            best = min(scores.values())
            chosen = min(d for d, s in scores.items() if s <= 1.01 * best)
        K = harmonics.count(chosen)
        coefficients = solve_normal(normal.gram.sum(axis=0)[:K, :K], normal.rhs.sum(axis=0)[:K])
        if iteration < ROBUST_ITERATIONS:  # Huber cut from a probe of the residuals under this fit
            rows = harmonics.gradient_rows((samples.positions[probe] - centre) / scale, chosen)
            cut = HUBER_K * 1.4826 * np.median(standardised_residual(samples, lever, probe, rows, coefficients))
            normal, weights = reweight_normal(unweighted, samples, lever, base, fold, folds, centre, scale, top,
                                        coefficients, cut, progress)
    outliers = int(np.sum(weights < base * (1 - 1e-12)))
    report = {"degree": chosen, "degree_chosen_by": "cross-validation" if degree is None else "user",
              "cv_rms_mm": 1000 * scores[chosen], "cv_rms_mm_by_degree": {str(d): 1000 * s for d, s in scores.items()},
              "cv_folds": folds, "outliers_downweighted": outliers}
    return HarmonicModel(centre, scale, chosen, coefficients), scores, weights, report
