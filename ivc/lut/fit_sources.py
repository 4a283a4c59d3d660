"""Equivalent sources: the secondary field of a large volume as the field of dipoles placed outside it.

A single solid-harmonic expansion about the centre (``ivc.lut.fit_harmonic``) converges only in
the ball that reaches the nearest metal; with metal a few centimetres beyond a head box's faces it
cannot hold over the whole box. Here every source column of ``G`` is instead the field of ``K``
point dipoles at fixed positions ``p_k`` outside the data, with unknown moments ``m_kj`` (3,):

    G[:, j](r) = Σ_k f_D(r − p_k) m_kj,        f_D(d) = (3 d̂ d̂ᵀ − I) / |d|³

Each term is the gradient of a harmonic potential away from ``p_k`` (``f_D`` is symmetric and
traceless), so the model is exactly curl- and divergence-free wherever there is no source: in the
whole mapped volume. The idea is that of equivalent sources for potential fields (Dampney 1969;
harmonica's ``EquivalentSources``): the moments follow from damped (Tikhonov) least squares on the
samples, the damping chosen by blocked cross-validation. The dipoles sit on two box-shaped shells
around the data: an inner one ``standoff`` beyond the data's bounding box at ``spacing`` (the
near metal) and a coarser outer one (distant metal and ferrous objects).

Weights, the cross-validation score and its folds are the harmonic fit's (``ivc.lut.samples``):
pose-equivalent millimetres, blocks of 500 frames. The fold normal equations are accumulated once,
so every damping is scored exactly for the cost of a few small solves.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve
from scipy.linalg.blas import dsyrk

from ivc import dipole
from ivc.errors import InputError
from ivc.lut.cross_validation import BlockedKFold
from ivc.lut.fitter import Fitter, register
from ivc.lut.samples import ERROR_FLOOR, FieldSamples
from ivc.table.grid import Grid

#: inner shell: distance beyond the data's bounding box and dipole spacing (m)
STANDOFF = 0.05
SPACING = 0.07
#: outer shell: distance beyond the bounding box and spacing (m)
OUTER_STANDOFF = 0.25
OUTER_SPACING = 0.2
#: relative Tikhonov dampings tried by cross-validation (on the unit-diagonal normal equations)
DAMPINGS = (1e-8, 1e-7, 1e-6, 1e-5)
CHUNK = 1_000
#: largest number of samples fitted (every k-th beyond it): the cost is samples x sources²
MAX_SAMPLES = 20_000
#: the fewest samples an equivalent-source fit takes
MIN_FIT_SAMPLES = 100


def check_max_samples(max_samples) -> None:
    """Refuse a sample cap that is not a whole number of at least :data:`MIN_FIT_SAMPLES`."""
    if not isinstance(max_samples, int | np.integer) or max_samples < MIN_FIT_SAMPLES:
        raise InputError(f"max_samples must be a whole number of at least {MIN_FIT_SAMPLES} (the fewest samples an "
                         f"equivalent-source fit takes), got {max_samples!r}")


def shell(low: np.ndarray, high: np.ndarray, standoff: float, spacing: float) -> np.ndarray:
    """Points (K, 3) on the six faces of the box ``[low − standoff, high + standoff]``, about ``spacing``
    apart (a regular grid on each face, edges and corners shared once)."""
    low = np.asarray(low, float) - standoff
    high = np.asarray(high, float) + standoff
    counts = np.maximum(np.ceil((high - low) / spacing).astype(int), 1) + 1
    axes = [np.linspace(low[a], high[a], counts[a]) for a in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    on_face = np.zeros(tuple(counts), dtype=bool)
    for a in range(3):
        index = [slice(None)] * 3
        for end in (0, -1):
            index[a] = end
            on_face[tuple(index)] = True
    return grid[on_face]


@dataclass
class SourceModel:
    """``G(r) = Σ_k f_D(r − p_k) m_k`` with ``positions`` (K, 3) m and ``moments`` (K, 3, 3): ``moments[k, :, j]``
    is dipole k's moment for source coil j (normalised dipole units · m³)."""

    positions: np.ndarray
    moments: np.ndarray

    def __call__(self, r: np.ndarray) -> np.ndarray:
        """G (..., 3, 3) at points r (..., 3), source frame (the compiled design rows times the moments)."""
        r = np.asarray(r, float)
        flat = r.reshape(-1, 3)
        coefficients = self.moments.reshape(-1, 3)
        G = np.empty((len(flat), 3, 3))
        for start in range(0, len(flat), CHUNK):
            G[start : start + CHUNK] = design_rows(flat[start : start + CHUNK], self.positions) @ coefficients
        return G.reshape(*r.shape[:-1], 3, 3)

    def value_and_jacobian(self, r: np.ndarray, jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """G (..., 3, 3) and ∂G_ij/∂r_k (..., 3, 3, 3) at r (..., 3)."""
        r = np.asarray(r, float)
        flat = r.reshape(-1, 3)
        G = np.empty((len(flat), 3, 3))
        dG = np.empty((len(flat), 3, 3, 3)) if jacobian else None
        m = self.moments
        for start in range(0, len(flat), CHUNK // 4 or 1):
            d = flat[start : start + CHUNK // 4, None, :] - self.positions[None]  # (n, K, 3)
            G[start : start + len(d)] = np.einsum("nkia,kaj->nij", dipole.field(d), m)
            if jacobian:
                dG[start : start + len(d)] = np.einsum("nkiac,kaj->nijc", dipole.field_jacobian(d), m)
        G = G.reshape(*r.shape[:-1], 3, 3)
        return G, (dG.reshape(*r.shape[:-1], 3, 3, 3) if jacobian else None)


@numba.njit(parallel=True, cache=True)
def _rows_kernel(points, sources, out):  # pragma: no cover - compiled
    for n in numba.prange(points.shape[0]):
        for k in range(sources.shape[0]):
            d0 = points[n, 0] - sources[k, 0]
            d1 = points[n, 1] - sources[k, 1]
            d2 = points[n, 2] - sources[k, 2]
            rho2 = d0 * d0 + d1 * d1 + d2 * d2
            inv3 = 1.0 / (rho2 * np.sqrt(rho2))
            three = 3.0 / rho2
            d = (d0, d1, d2)
            for i in range(3):
                for a in range(3):
                    value = three * d[i] * d[a]
                    if i == a:
                        value -= 1.0
                    out[n, i, 3 * k + a] = value * inv3


def design_rows(points: np.ndarray, sources: np.ndarray) -> np.ndarray:
    """Design rows (n, 3, 3K): row (sample, component i), column (source k, moment axis a) = f_D(r − p_k)[i, a]."""
    out = np.empty((len(points), 3, 3 * len(sources)))
    _rows_kernel(np.ascontiguousarray(points, dtype=float), np.ascontiguousarray(sources, dtype=float), out)
    return out


def damped_solve(gram: np.ndarray, rhs: np.ndarray, damping: float) -> np.ndarray:
    """``(D⁻¹ gram D⁻¹ + damping I)⁻¹`` applied in the unit-diagonal scaling ``D = sqrt(diag(gram))``."""
    scale = np.sqrt(np.maximum(np.diag(gram), 1e-300))
    scaled = gram / np.outer(scale, scale)
    scaled[np.diag_indices_from(scaled)] += damping
    try:  # symmetric positive definite with any damping > 0: Cholesky, half the cost of an LU solve
        factor = cho_factor(scaled, lower=False, overwrite_a=True, check_finite=False)
        return cho_solve(factor, rhs / scale[:, None], check_finite=False) / scale[:, None]
    except LinAlgError:  # lost definiteness to round-off: the general solve
        scaled = gram / np.outer(scale, scale)
        scaled[np.diag_indices_from(scaled)] += damping
        return np.linalg.solve(scaled, rhs / scale[:, None]) / scale[:, None]


def default_sources(positions: np.ndarray, standoff: float = STANDOFF, spacing: float = SPACING,
                    outer_standoff: float = OUTER_STANDOFF, outer_spacing: float = OUTER_SPACING) -> np.ndarray:
    """The two shells of dipoles around the bounding box of ``positions`` (N, 3)."""
    low, high = positions.min(axis=0), positions.max(axis=0)
    return np.concatenate([shell(low, high, standoff, spacing), shell(low, high, outer_standoff, outer_spacing)])


@dataclass
class NormalEquations:
    """The fold normal equations of an equivalent-source fit (:func:`normal_equations`): per fold f,
    ``gram[f] = XᵀWX`` (3K, 3K), ``rhs[f] = XᵀWY`` (3K, 3), ``yy[f] = YᵀWY`` and ``count[f]`` (the CV
    score's normaliser), for the ``sources`` (K, 3) m; ``samples_used``, ``sample_stride``,
    ``nearest_source_mm`` and the weights' ``error_floor`` (m) for the report."""

    sources: np.ndarray
    gram: np.ndarray
    rhs: np.ndarray
    yy: np.ndarray
    count: np.ndarray
    samples_used: int
    sample_stride: int
    nearest_source_mm: float
    error_floor: float = ERROR_FLOOR


def even_subset(positions: np.ndarray, max_samples: int, cell: float, seed: int = 0) -> np.ndarray:
    """Indices (sorted) of at most ``max_samples`` of the points (N, 3) m spread evenly over space: the points
    are binned in cubes of ``cell`` m and each cube keeps at most ``c`` of its points (in a fixed random
    order), ``c`` the largest that keeps the total within ``max_samples``, the rest of the budget one more
    from each of an even draw of the cubes holding more than ``c``: a dense region (the cube sweep's
    ball) gives up samples before a sparse one (the far faces, reached by one sensor of the wand)."""
    positions = np.asarray(positions, float)
    if len(positions) <= max_samples:
        return np.arange(len(positions))
    if not (np.isfinite(cell) and cell > 0):
        raise InputError(f"the selection's cell must be a positive number of metres, got {cell!r}")
    keys = np.floor((positions - positions.min(axis=0)) / cell).astype(np.int64)
    _, box, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    box = box.reshape(-1)
    low, high = 0, int(counts.max())  # the largest cap c with sum(min(counts, c)) <= max_samples
    while low < high:
        middle = (low + high + 1) // 2
        if np.minimum(counts, middle).sum() <= max_samples:
            low = middle
        else:
            high = middle - 1
    order = np.random.default_rng(seed).permutation(len(positions))
    order = order[np.argsort(box[order], kind="stable")]  # by cube, random within it
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(len(positions)) - starts[box[order]]
    chosen = order[rank < low]
    spare = max_samples - len(chosen)  # filled with one more from each of an even draw of the fuller cubes
    more = order[rank == low]
    if spare > 0 and len(more):
        chosen = np.concatenate([chosen, more[np.linspace(0, len(more) - 1, min(spare, len(more))).astype(int)]])
    return np.sort(chosen)


def normal_equations(samples: FieldSamples, sources: np.ndarray | None = None, folds: int = 5,
                     max_samples: int = MAX_SAMPLES, progress: Callable[[int], None] | None = None,
                     block_frames: int = 500, even_cell: float | None = None,
                     error_floor: float = ERROR_FLOOR) -> NormalEquations:
    """Accumulate the fold normal equations of :func:`fit_sources` (its arguments; the costly part of a fit:
    samples x sources²). Solving them for any number of dampings is :func:`solve_normal_equations`.
    Beyond ``max_samples`` every k-th sample is fitted, or with ``even_cell`` (m) the samples of
    :func:`even_subset` (``sample_stride`` is then 0 in the report). ``error_floor`` (m): the ``ε_0`` of the
    samples' weights ``λ² / (ε² + ε_0²)`` (:meth:`~ivc.lut.samples.FieldSamples.weights`)."""
    if not (np.isfinite(error_floor) and error_floor > 0):
        raise InputError(f"the error floor must be a positive number of metres, got {error_floor!r}")
    if len(samples) < MIN_FIT_SAMPLES:
        raise InputError(f"{len(samples)} samples are too few for an equivalent-source fit")
    stride = max(1, -(-len(samples) // max_samples))
    if stride > 1 and even_cell is not None:
        samples, stride = samples.subset(even_subset(samples.positions, max_samples, even_cell)), 0
    elif stride > 1:
        samples = samples.subset(np.arange(0, len(samples), stride))
    if sources is None:
        sources = default_sources(samples.positions)
    sources = np.asarray(sources, float)
    if sources.ndim != 2 or sources.shape[1] != 3 or len(sources) == 0:
        raise InputError(f"sources must be a non-empty (K, 3) array of positions, got shape {sources.shape}")
    nearest = _nearest_distance(samples.positions, sources)
    if nearest < 1e-3:
        raise InputError(f"an equivalent source lies {1000 * nearest:.2g} mm from a sample: sources must stay "
                         "outside the mapped volume")
    K = 3 * len(sources)
    fold = samples.folds(folds, block_frames)
    weight = samples.weights(error_floor)
    lever = samples.leverage()
    gram = np.zeros((folds, K, K))
    rhs = np.zeros((folds, K, 3))
    yy = np.zeros(folds)
    count = np.zeros(folds)
    for f in range(folds):
        members = np.flatnonzero(fold == f)
        for start in range(0, len(members), CHUNK):
            part = members[start : start + CHUNK]
            root = np.sqrt(weight[part])
            X = (design_rows(samples.positions[part], sources) * root[:, None, None]).reshape(-1, K)
            Y = (samples.fields[part] * root[:, None, None]).reshape(-1, 3)
            gram[f] += dsyrk(1.0, X.T, trans=0)  # the upper triangle (the lower stays zero)
            rhs[f] += X.T @ Y
            yy[f] += np.sum(Y**2)
            count[f] += np.sum(weight[part] / lever[part] ** 2)
            if progress is not None:
                progress(len(part))
        gram[f] += np.triu(gram[f], 1).T  # symmetrised once per fold, not per block
    return NormalEquations(sources, gram, rhs, yy, count, len(samples), stride, 1000 * nearest, error_floor)


def solve_normal_equations(normal: NormalEquations, dampings=DAMPINGS) -> tuple[SourceModel, dict]:
    """The model and report of :func:`fit_sources` from its accumulated normal equations: the damping is
    the lowest-scoring of ``dampings`` in the folds' cross-validation; a single damping is used as given."""
    gram, rhs, yy, count = normal.gram, normal.rhs, normal.yy, normal.count
    total_gram, total_rhs = gram.sum(axis=0), rhs.sum(axis=0)
    scores = {}
    for damping in dampings if len(dampings) > 1 else ():  # a single damping is used as given
        sse = 0.0
        for f in range(len(gram)):
            if count[f] == 0:
                continue
            c = damped_solve(total_gram - gram[f], total_rhs - rhs[f], damping)
            sse += yy[f] - 2 * np.sum(c * rhs[f]) + np.sum(c * (gram[f] @ c))
        scores[damping] = float(np.sqrt(max(sse, 0.0) / count.sum()))
    chosen = min(scores, key=scores.get) if scores else float(dampings[0])
    coefficients = damped_solve(total_gram, total_rhs, chosen)  # (3K, 3): row (k, a), column j
    sources = normal.sources
    model = SourceModel(sources, coefficients.reshape(len(sources), 3, 3))
    report = {"sources": len(sources), "damping": chosen,
              "damping_chosen_by": "cross-validation" if scores else "given",
              "cv_rms_mm": 1000 * scores[chosen] if scores else None,
              "cv_rms_mm_by_damping": {f"{d:g}": 1000 * s for d, s in scores.items()},
              "cv_folds": len(gram), "samples_used": normal.samples_used, "sample_stride": normal.sample_stride,
              "nearest_source_mm": normal.nearest_source_mm, "error_floor_mm": 1000 * normal.error_floor}
    return model, report


def fit_sources(samples: FieldSamples, sources: np.ndarray | None = None, dampings=DAMPINGS, folds: int = 5,
                max_samples: int = MAX_SAMPLES, progress: Callable[[int], None] | None = None,
                block_frames: int = 500, even_cell: float | None = None,
                error_floor: float = ERROR_FLOOR) -> tuple[SourceModel, dict]:
    """Fit the dipole moments of ``sources`` (K, 3) m (default: :func:`default_sources` around the samples).

    Weighted damped least squares with the samples' pose-equivalent weights; the damping is the lowest-scoring
    of ``dampings`` in ``folds``-fold cross-validation over blocks of frames (held out together); a single
    damping is used as given, without cross-validation. At most
    ``max_samples`` samples are used (every k-th, or with ``even_cell`` spread evenly over space:
    :func:`even_subset`); ``error_floor`` is the weights' ``ε_0`` (m, :func:`normal_equations`). Returns the
    model and a report (sources, damping chosen, CV score per damping, mm)."""
    normal = normal_equations(samples, sources, folds, max_samples, progress, block_frames, even_cell, error_floor)
    return solve_normal_equations(normal, dampings)


def _nearest_distance(points: np.ndarray, sources: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    return float(cKDTree(sources).query(points, k=1)[0].min())


@register
class SourcesFit(Fitter):
    """Equivalent sources as a :class:`~ivc.lut.fitter.Fitter` (``ivc fit --method sources``).

    ``standoff``, ``spacing``: the inner shell of dipoles beyond the samples' bounding box (m);
    ``outer_standoff``, ``outer_spacing``: the outer shell; ``dampings``: the Tikhonov dampings
    scored by ``cv`` (a single one is used as given); ``max_samples``: the samples fitted (every
    k-th beyond). Fitted attributes: ``model_`` (:class:`SourceModel`), ``damping_``, ``cv_score_``
    (m, exact from the fold normal equations) and ``report_``.
    """

    name = "sources"

    def __init__(self, standoff: float = STANDOFF, spacing: float = SPACING, outer_standoff: float = OUTER_STANDOFF,
                 outer_spacing: float = OUTER_SPACING, dampings: tuple = DAMPINGS, max_samples: int = MAX_SAMPLES,
                 cv: BlockedKFold | None = None):
        for key, value in (("standoff", standoff), ("spacing", spacing), ("outer_standoff", outer_standoff),
                           ("outer_spacing", outer_spacing)):
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"{key} must be a positive number of metres, got {value!r}")
        dampings = tuple(float(d) for d in dampings)
        if not dampings or not all(np.isfinite(d) and d > 0 for d in dampings):
            raise InputError(f"dampings must be positive numbers, got {dampings!r}")
        check_max_samples(max_samples)
        self.standoff, self.spacing = standoff, spacing
        self.outer_standoff, self.outer_spacing = outer_standoff, outer_spacing
        self.dampings, self.max_samples = dampings, max_samples
        self.cv = BlockedKFold() if cv is None else cv

    def progress_units(self, samples: FieldSamples) -> int:
        return min(len(samples), self.max_samples)

    def fit(self, samples: FieldSamples, grid: Grid | None = None,
            progress: Callable[[int], None] | None = None) -> SourcesFit:
        sources = default_sources(samples.positions, self.standoff, self.spacing, self.outer_standoff,
                                  self.outer_spacing)
        model, report = fit_sources(samples, sources, self.dampings, self.cv.k, self.max_samples, progress,
                                    self.cv.block_frames)
        self.model_, self.damping_, self.report_ = model, report["damping"], report
        cv = report["cv_rms_mm"]
        self.cv_score_ = None if cv is None else cv / 1000
        self._fitted_to = samples
        return self

    def cross_validate(self, samples: FieldSamples, grid: Grid | None = None) -> float:
        """``cv_score_`` for the samples of the fit (when the damping was cross-validated); else refit per fold."""
        if getattr(self, "_fitted_to", None) is samples and self.cv_score_ is not None:
            return self.cv_score_
        return super().cross_validate(samples, grid)
