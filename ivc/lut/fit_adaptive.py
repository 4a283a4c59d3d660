"""A field model that adapts to the room: a solid-harmonic expansion, or one plus a layer of equivalent dipoles.

A single solid-harmonic expansion about the data's centre (:mod:`ivc.lut.fit_harmonic`) converges only inside
the ball that reaches the nearest induced source. Where strong metal stands a few centimetres beyond the mapped
ball, that ball is the mapped one only just, the expansion's terms fall off as ``(R / (R + d))^l`` and no degree
a sweep can pin down follows the field: the harmonic fit then mistakes the clean samples nearest the metal for
outliers. Here the blocked cross-validation chooses between

- ``harmonic``: the expansion of degree 1..``max_degree`` (16) alone; when it wins, the harmonic fit itself is
  fitted to every sample with degrees up to two beyond the best on the scoring samples (near strong metal the
  held-out score keeps falling beyond the default fit's 10), and
- ``harmonic + dipoles``: a low-degree expansion (degree ``degree``: the distant metal) plus point dipoles on a
  sphere ``standoff`` beyond the data's enclosing ball, about ``standoff`` apart (the near metal), one
  candidate per standoff in ``standoffs``; the damping of the dipoles' moments is chosen too.

Both are exactly curl- and divergence-free in the whole mapped volume: each harmonic term is the gradient of a
harmonic polynomial, each dipole term ``f_D(r − p) m`` the gradient of a harmonic potential away from ``p``, and
no source lies in the ball (docs/strong-rooms.md). Equivalent sources are Dampney's (1969); the layer's depth,
its spacing and the damping are the cross-validated choices harmonica's ``EquivalentSources`` leaves to the user.

Every candidate is scored on the same samples (at most ``max_samples``, spread evenly over space by
:func:`ivc.lut.fit_sources.even_subset`) with the same folds (:class:`~ivc.lut.cross_validation.BlockedKFold`),
exactly from the fold normal equations. Outliers are down-weighted as in the harmonic fit (Huber, cut at 3 robust
standard deviations, two rounds), but under the chosen model: a sample the model cannot follow first makes a
larger model win, and only what is left is called an outlier.
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
from ivc.lut.fit_harmonic import HarmonicFit, HarmonicModel
from ivc.lut.fit_harmonic import NormalEquations as HarmonicNormal
from ivc.lut.fit_harmonic import cv_scores as harmonic_scores
from ivc.lut.fit_sources import SourceModel, damped_solve, design_rows, even_subset
from ivc.lut.fitter import Fitter, register
from ivc.lut.samples import ERROR_FLOOR, FieldSamples
from ivc.table.grid import DEFAULT_SPACING, Grid

#: candidate depths of the dipole layer beyond the data's enclosing ball (m)
STANDOFFS = (0.05, 0.08, 0.12)
#: degree of the harmonic expansion beside the dipoles (the distant metal)
HYBRID_DEGREE = 8
#: dipole spacing on the layer as a multiple of its depth, and the most dipoles per layer
SPACING_RATIO = 1.0
MAX_SOURCES = 300
#: largest degree of the pure expansion among the candidates (the harmonic fit's own default stops at 10; near
#: strong metal the held-out score keeps falling beyond it)
ADAPTIVE_MAX_DEGREE = 16
#: Tikhonov dampings of the dipole layers (relative, on the unit-diagonal normal equations)
LAYER_DAMPINGS = (1e-10, 1e-9, 1e-8, 1e-7, 1e-6)
#: samples the candidates are scored and the dipoles fitted on
MAX_SAMPLES = 12_000
#: the harmonic expansion is kept unless a layer beats its held-out score by more than this fraction
PREFER_HARMONIC = 0.02
HUBER_K = 3.0
ROBUST_ITERATIONS = 2
CHUNK = 1_000


def sphere_points(n: int) -> np.ndarray:
    """``n`` points (n, 3) spread evenly over the unit sphere (the Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5**0.5) * k
    rho = np.sqrt(1 - z**2)
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=-1)


def dipole_layer(centre: np.ndarray, radius: float, standoff: float, spacing_ratio: float = SPACING_RATIO,
                 max_sources: int = MAX_SOURCES) -> np.ndarray:
    """Dipole positions (K, 3) m on the sphere of radius ``radius + standoff`` about ``centre``, about
    ``spacing_ratio · standoff`` apart (at most ``max_sources``)."""
    outer = radius + standoff
    n = int(np.clip(round(4 * np.pi * outer**2 / (spacing_ratio * standoff) ** 2), 12, max_sources))
    return np.asarray(centre, float) + outer * sphere_points(n)


@dataclass
class HybridModel:
    """``G(r)``: the harmonic expansion ``harmonic`` plus the dipoles ``sources`` (either may be None)."""

    harmonic: HarmonicModel | None
    sources: SourceModel | None

    def __call__(self, r: np.ndarray) -> np.ndarray:
        r = np.asarray(r, float)
        out = np.zeros((*r.shape[:-1], 3, 3))
        if self.harmonic is not None:
            out += self.harmonic(r)
        if self.sources is not None:
            out += self.sources(r)
        return out


def _rows(points: np.ndarray, centre: np.ndarray, scale: float, degree: int, sources: np.ndarray) -> np.ndarray:
    """Design rows (n, 3, K_h + 3 K_s): the harmonic basis gradients of degree 1..degree, then the dipoles'."""
    parts = [harmonics.gradient_rows((points - centre) / scale, degree)]
    if len(sources):
        parts.append(design_rows(points, sources))
    return np.concatenate(parts, axis=-1)


@dataclass
class _Normal:
    """Fold normal equations (per fold f): gram (k, K, K), rhs (k, K, 3), yy (k,), count (k,)."""

    gram: np.ndarray
    rhs: np.ndarray
    yy: np.ndarray
    count: np.ndarray


def accumulate(samples: FieldSamples, weight: np.ndarray, fold: np.ndarray, k: int, centre, scale, degree,
                sources) -> _Normal:
    lever = samples.leverage()
    K = harmonics.count(degree) + 3 * len(sources)
    normal = _Normal(np.zeros((k, K, K)), np.zeros((k, K, 3)), np.zeros(k), np.zeros(k))
    for f in range(k):
        members = np.flatnonzero(fold == f)
        for start in range(0, len(members), CHUNK):
            part = members[start : start + CHUNK]
            root = np.sqrt(weight[part])
            X = (_rows(samples.positions[part], centre, scale, degree, sources) * root[:, None, None]).reshape(-1, K)
            Y = (samples.fields[part] * root[:, None, None]).reshape(-1, 3)
            normal.gram[f] += dsyrk(1.0, X.T, trans=0)
            normal.rhs[f] += X.T @ Y
            normal.yy[f] += np.sum(Y**2)
            normal.count[f] += np.sum(weight[part] / lever[part] ** 2)
        normal.gram[f] += np.triu(normal.gram[f], 1).T
    return normal


def damped_scores(normal: _Normal, dampings) -> dict[float, float]:
    """Held-out pose-equivalent RMS (m) per damping, exactly from the fold normal equations."""
    total_gram, total_rhs = normal.gram.sum(axis=0), normal.rhs.sum(axis=0)
    scores = {}
    for damping in dampings:
        sse = 0.0
        for f in range(len(normal.gram)):
            if normal.count[f] == 0:
                continue
            c = damped_solve(total_gram - normal.gram[f], total_rhs - normal.rhs[f], damping)
            sse += normal.yy[f] - 2 * np.sum(c * normal.rhs[f]) + np.sum(c * (normal.gram[f] @ c))
        scores[damping] = float(np.sqrt(max(sse, 0.0) / normal.count.sum()))
    return scores


def _residual(samples: FieldSamples, model: HybridModel) -> np.ndarray:
    """Standardised residual ``λ |G_model − G|_F / σ`` of every sample (the harmonic fit's Huber currency)."""
    sigma = np.sqrt(samples.error**2 + ERROR_FLOOR**2)
    return samples.leverage() * np.linalg.norm(model(samples.positions) - samples.fields, axis=(1, 2)) / sigma


#: a region whose residual exceeds the whole ball's by this factor is named in the fit's advice
REGION_FACTOR = 2.0
_FACES = ("+x", "-x", "+y", "-y", "+z", "-z")


def residual_structure(samples: FieldSamples, model, centre: np.ndarray, radius: float) -> dict:
    """Where in the volume ``model`` fails: the pose-equivalent RMS residual (mm) of ``samples`` in the inner
    half of the ball and in each sixth of its outer half (by the axis the sample lies furthest along, source
    frame), with advice when a region's residual is more than :data:`REGION_FACTOR` times the whole ball's."""
    offset = samples.positions - centre
    distance = np.linalg.norm(offset, axis=1)
    residual = samples.leverage() * np.linalg.norm(model(samples.positions) - samples.fields, axis=(1, 2))
    axis = np.argmax(np.abs(offset), axis=1)
    face = 2 * axis + (np.take_along_axis(offset, axis[:, None], 1)[:, 0] < 0)
    region = np.where(distance < 0.5 * radius, -1, face)
    overall = float(np.sqrt(np.mean(residual**2)))
    rows = {}
    for key in range(-1, 6):
        inside = region == key
        if inside.sum() >= 20:
            rows["inner half" if key < 0 else f"outer half, {_FACES[key]} side"] = {
                "rms_mm": 1000 * float(np.sqrt(np.mean(residual[inside] ** 2))), "samples": int(inside.sum())}
    worst = [name for name, row in rows.items() if row["rms_mm"] > REGION_FACTOR * 1000 * overall]
    advice = (f"the model misses most in the {', '.join(worst)} of the mapped ball (more than {REGION_FACTOR:g}x "
              "the ball's residual): sweep more there, or record an extension sweep on that side"
              if worst else "no region's residual exceeds the ball's by more than "
              f"{REGION_FACTOR:g}x")
    return {"rms_mm": 1000 * overall, "regions": rows, "advice": advice}


@register
class AdaptiveFit(Fitter):
    """The model chosen by the data (``ivc fit --method adaptive``): the harmonic expansion, or a low-degree one
    plus a layer of equivalent dipoles, whichever blocked cross-validation prefers (module docstring).

    ``standoffs`` (m): the candidate depths of the dipole layer beyond the data's enclosing ball; ``degree``: the
    expansion beside the dipoles; ``max_degree``: the pure expansion's largest degree; ``dampings``: the dipole
    moments' Tikhonov dampings; ``max_samples``: the samples the candidates are scored on. Fitted attributes:
    ``model_`` (:class:`HybridModel`), ``choice_`` (``"harmonic"`` or ``"harmonic + dipoles"``), ``scores_``
    (held-out score per candidate, m), ``cv_score_`` (m) and ``report_`` (with ``model_choice``, a sentence).
    """

    name = "adaptive"

    def __init__(self, standoffs: tuple = STANDOFFS, degree: int = HYBRID_DEGREE, max_degree: int = ADAPTIVE_MAX_DEGREE,
                 dampings: tuple = LAYER_DAMPINGS, max_samples: int = MAX_SAMPLES, cv: BlockedKFold | None = None):
        standoffs = tuple(float(s) for s in standoffs)
        if not standoffs or not all(np.isfinite(s) and s > 0 for s in standoffs):
            raise InputError(f"standoffs must be positive numbers of metres, got {standoffs!r}")
        for key, value in (("degree", degree), ("max_degree", max_degree)):
            if not isinstance(value, int | np.integer) or value < 1:
                raise InputError(f"{key} must be a whole number of at least 1, got {value!r}")
        dampings = tuple(float(d) for d in dampings)
        if not dampings or not all(np.isfinite(d) and d > 0 for d in dampings):
            raise InputError(f"dampings must be positive numbers, got {dampings!r}")
        if not isinstance(max_samples, int | np.integer) or max_samples < 1_000:
            raise InputError(f"max_samples must be a whole number of at least 1000, got {max_samples!r}")
        self.standoffs, self.degree, self.max_degree = standoffs, degree, max_degree
        self.dampings, self.max_samples = dampings, max_samples
        self.cv = BlockedKFold() if cv is None else cv

    @property
    def progress_label(self) -> str:
        return f"fitting (adaptive: harmonic or harmonic + dipoles, {len(self.standoffs)} layers)"

    def fit(self, samples: FieldSamples, grid: Grid | None = None,
            progress: Callable[[int], None] | None = None) -> AdaptiveFit:
        with threadpool_limits(limits=1, user_api="blas"):
            self._fit(samples, progress)
        self._fitted_to = samples
        return self

    def _fit(self, samples: FieldSamples, progress) -> None:
        if len(samples) < 3 * harmonics.count(2):
            raise InputError(f"{len(samples)} samples are too few for a harmonic fit")
        subset = samples.subset(even_subset(samples.positions, self.max_samples, DEFAULT_SPACING))
        centre = 0.5 * (samples.positions.min(axis=0) + samples.positions.max(axis=0))
        radius = float(np.max(np.linalg.norm(samples.positions - centre, axis=1)))
        fold, k = self.cv.folds(subset), self.cv.k
        weight = subset.weights()
        top = max(self.max_degree, self.degree)
        # the pure expansion, scored on the subset (its degree prefix); each layer beside degree `self.degree`
        pure = accumulate(subset, weight, fold, k, centre, radius, top, np.empty((0, 3)))
        by_degree = harmonic_scores(HarmonicNormal(pure.gram, pure.rhs, pure.yy, pure.count), top)
        best_degree = min(by_degree, key=by_degree.get)
        scores = {"harmonic": by_degree[best_degree]}
        layers, normals, damping_scores = {}, {}, {}
        for standoff in self.standoffs:
            label = f"harmonic {self.degree} + dipoles {1000 * standoff:.0f} mm"
            layers[label] = dipole_layer(centre, radius, standoff)
            normals[label] = accumulate(subset, weight, fold, k, centre, radius, self.degree, layers[label])
            damping_scores[label] = damped_scores(normals[label], self.dampings)
            scores[label] = min(damping_scores[label].values())
            if progress is not None:
                progress(len(subset))
        hybrid = min((label for label in scores if label != "harmonic"), key=scores.get)
        if scores[hybrid] < (1 - PREFER_HARMONIC) * scores["harmonic"]:
            # where the chosen layer still misses (samples beyond the Huber cut), a finer, nearer layer over
            # that part of the sphere only: kept when it lowers the held-out score
            standoff = float(hybrid.split()[-2]) / 1000
            cap = self._cap(subset, weight, centre, radius, layers[hybrid], normals[hybrid],
                            min(damping_scores[hybrid], key=damping_scores[hybrid].get), standoff)
            if len(cap):
                label = f"{hybrid} + {len(cap)} at {1000 * standoff / 2:.0f} mm"
                layers[label] = np.concatenate([layers[hybrid], cap])
                normals[label] = accumulate(subset, weight, fold, k, centre, radius, self.degree, layers[label])
                damping_scores[label] = damped_scores(normals[label], self.dampings)
                scores[label] = min(damping_scores[label].values())
                if scores[label] < (1 - PREFER_HARMONIC) * scores[hybrid]:
                    hybrid = label
            self._fit_hybrid(subset, weight, fold, k, centre, radius, layers[hybrid], normals[hybrid],
                             damping_scores[hybrid], standoff)
            why = (f"harmonic {self.degree} + {len(layers[hybrid])} dipoles ({hybrid}): held-out "
                   f"{1000 * scores[hybrid]:.4f} mm against the harmonic expansion's "
                   f"{1000 * scores['harmonic']:.4f} mm (degree {best_degree}): metal near the mapped ball")
            self.choice_ = "harmonic + dipoles"
        else:
            # every sample, degrees up to two beyond the subset's best (the harmonic fit's own CV picks)
            self.harmonic_max_degree_ = min(self.max_degree, best_degree + 2)
            harmonic = HarmonicFit(None, self.harmonic_max_degree_, self.cv).fit(samples)
            self.model_ = HybridModel(harmonic.model_, None)
            self.weights_, self.cv_score_ = harmonic.weights_, harmonic.cv_score_
            self.report_ = dict(harmonic.report_)
            why = (f"harmonic expansion (degree {harmonic.degree_}): held-out {1000 * scores['harmonic']:.4f} mm, "
                   f"no dipole layer better by {100 * PREFER_HARMONIC:g} % (best {hybrid}: "
                   f"{1000 * scores[hybrid]:.4f} mm)")
            self.choice_ = "harmonic"
        self.scores_ = scores
        self.report_["residual_structure"] = residual_structure(subset, self.model_, centre, radius)
        self.report_.update(model=self.choice_, model_choice=why,
                            cv_rms_mm_by_model={label: 1000 * s for label, s in scores.items()},
                            model_scored_on_samples=len(subset))

    def _cap(self, subset, weight, centre, radius, layer, normal, damping, standoff) -> np.ndarray:
        """Dipoles (M, 3) half as deep and half as far apart as ``layer``'s, over the part of the sphere facing
        the samples ``layer`` misses (standardised residual beyond the Huber cut, in the outer half of the ball);
        at most :data:`MAX_SOURCES`, nearest the worst first."""
        coefficients = damped_solve(normal.gram.sum(axis=0), normal.rhs.sum(axis=0), damping)
        Kh = harmonics.count(self.degree)
        model = HybridModel(HarmonicModel(centre, radius, self.degree, coefficients[:Kh]),
                            SourceModel(layer, coefficients[Kh:].reshape(len(layer), 3, 3)))
        residual = _residual(subset, model)
        offset = subset.positions - centre
        distance = np.linalg.norm(offset, axis=1)
        missed = (residual > HUBER_K * 1.4826 * np.median(residual)) & (distance > 0.5 * radius)
        if not missed.any():
            return np.empty((0, 3))
        depth = max(standoff / 2, 0.015)
        fine = dipole_layer(centre, radius, depth, SPACING_RATIO, 100_000)
        unit = (fine - centre) / (radius + depth)
        towards = offset[missed] / distance[missed, None]
        cosine = unit @ towards.T  # (M, missed)
        reach = np.cos(min(np.pi, 2 * standoff / radius))  # within two coarse depths of arc of a missed sample
        near = (cosine >= reach).any(axis=1)
        worst = np.where(cosine >= reach, residual[missed][None], 0.0).max(axis=1)
        chosen = np.flatnonzero(near)
        chosen = chosen[np.argsort(-worst[chosen], kind="stable")][:MAX_SOURCES]
        return fine[np.sort(chosen)]

    def _fit_hybrid(self, subset, weight, fold, k, centre, radius, sources, normal, damping_scores, standoff) -> None:
        Kh = harmonics.count(self.degree)
        base = normal
        weights = weight
        damping = min(damping_scores, key=damping_scores.get)
        for iteration in range(ROBUST_ITERATIONS + 1):
            coefficients = damped_solve(normal.gram.sum(axis=0), normal.rhs.sum(axis=0), damping)
            model = HybridModel(HarmonicModel(centre, radius, self.degree, coefficients[:Kh]),
                                SourceModel(sources, coefficients[Kh:].reshape(len(sources), 3, 3)))
            if iteration == ROBUST_ITERATIONS:
                break
            residual = _residual(subset, model)
            cut = HUBER_K * 1.4826 * np.median(residual)
            factor = np.minimum(1.0, cut / np.maximum(residual, 1e-300))
            weights = weight * factor
            reduced = np.flatnonzero(factor < 1.0)
            normal = _Normal(base.gram.copy(), base.rhs.copy(), base.yy.copy(), base.count.copy())
            if len(reduced):  # remove the reduced part of the outliers' weight from the base equations
                removed = accumulate(subset.subset(reduced), weight[reduced] * (1 - factor[reduced]), fold[reduced],
                                      k, centre, radius, self.degree, sources)
                for name in ("gram", "rhs", "yy", "count"):
                    setattr(normal, name, getattr(normal, name) - getattr(removed, name))
            damping_scores = damped_scores(normal, self.dampings)
            damping = min(damping_scores, key=damping_scores.get)
        outliers = int(np.sum(weights < weight * (1 - 1e-12)))
        self.model_, self.weights_ = model, weights
        self.cv_score_ = damping_scores[damping]
        self.report_ = {"degree": self.degree, "degree_chosen_by": "adaptive", "sources": len(sources),
                        "standoff_mm": 1000 * standoff, "damping": damping,
                        "cv_rms_mm": 1000 * self.cv_score_,
                        "cv_rms_mm_by_damping": {f"{d:g}": 1000 * s for d, s in damping_scores.items()},
                        "cv_folds": k, "outliers_downweighted": outliers,
                        "outlier_share": outliers / len(subset)}
        # each dipole's depth below the data: a node nearer a dipole than half its depth is not tabulated
        from scipy.spatial import cKDTree

        self._sources, self._depths = sources, cKDTree(subset.positions).query(sources)[0]

    def tabulate(self, grid: Grid) -> np.ndarray:
        """Node values; nodes nearer the dipole layer than half its depth below the data are NaN (never
        mapped): there the layer's own near field is no map of the room."""
        nodes = grid.nodes()
        values = self.predict(nodes)
        if self.choice_ == "harmonic + dipoles":
            from scipy.spatial import cKDTree

            distance, nearest = cKDTree(self._sources).query(nodes.reshape(-1, 3))
            values.reshape(-1, 3, 3)[distance < 0.5 * self._depths[nearest]] = np.nan
        return values

    def cross_validate(self, samples: FieldSamples, grid: Grid | None = None) -> float:
        """``cv_score_`` for the samples of the fit (exact from its fold normal equations); else refit per fold."""
        if getattr(self, "_fitted_to", None) is samples:
            return self.cv_score_
        return super().cross_validate(samples, grid)
