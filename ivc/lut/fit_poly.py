"""Himberg 2010's fit: local weighted polynomial regression at every grid node (eq. 105-107, docs/math.md §8).

For node ``r_gp`` the samples within ``radius`` (Himberg 2010: 38.1 mm) fit each of the nine
components of ``G`` with a polynomial of ``degree`` in ``(r − r_gp) / radius``, weighted;
the node value is the constant term, ``G(r_gp) = f_P(0)ᵀ C``. The normal equations of
eq. 106 are solved as a least-squares problem, never by forming an inverse.

A polynomial fitted to samples on one side of a node extrapolates to it, wildly at the
edge of the data; so a node is fitted only when its neighbourhood has at least three
samples per coefficient and samples in at least ``MIN_OCTANTS`` of the eight octants
around it. Other nodes are left unfitted (NaN, invalid).
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import combinations_with_replacement

import numpy as np
from scipy.spatial import cKDTree

from ivc.errors import InputError
from ivc.lut.cross_validation import BlockedKFold
from ivc.lut.fitter import Fitter, register
from ivc.lut.samples import FieldSamples
from ivc.table.grid import Grid, GridField

#: the polynomial degree unless one is given
DEFAULT_DEGREE = 2
SAMPLES_PER_COEFFICIENT = 3
MIN_OCTANTS = 8
MIN_PER_OCTANT = 3


def monomials(x: np.ndarray, degree: int) -> np.ndarray:
    """``f_P(x)`` (N, T): all monomials of x (N, 3) up to ``degree``, the constant first."""
    columns = [np.ones(len(x))]
    for d in range(1, degree + 1):
        for combo in combinations_with_replacement(range(3), d):
            columns.append(np.prod(x[:, list(combo)], axis=1))
    return np.stack(columns, axis=1)


def fit_poly(samples: FieldSamples, grid: Grid, degree: int = 2, radius: float | None = None,
             weights: np.ndarray | None = None, progress: Callable[[int], None] | None = None) -> np.ndarray:
    """Node values (nx, ny, nz, 3, 3), NaN where a node has too little data."""
    radius = grid.spacing if radius is None else radius
    weights = samples.weights() if weights is None else weights
    nodes = grid.nodes().reshape(-1, 3)
    terms = monomials(np.zeros((1, 3)), degree).shape[1]
    values = np.full((len(nodes), 9), np.nan)
    tree = cKDTree(samples.positions)
    neighbours = tree.query_ball_point(nodes, radius)
    targets = samples.fields.reshape(-1, 9)
    for n, index in enumerate(neighbours):
        if len(index) >= SAMPLES_PER_COEFFICIENT * terms:
            index = np.asarray(index)
            offset = samples.positions[index] - nodes[n]
            octant = (offset[:, 0] > 0) * 4 + (offset[:, 1] > 0) * 2 + (offset[:, 2] > 0)
            if np.sum(np.bincount(octant, minlength=8) >= MIN_PER_OCTANT) < MIN_OCTANTS:
                continue
            root = np.sqrt(weights[index])[:, None]
            design = monomials(offset / radius, degree) * root
            coefficients, _, rank, _ = np.linalg.lstsq(design, targets[index] * root, rcond=None)
            if rank == terms:
                values[n] = coefficients[0]
        if progress is not None and n % 256 == 255:
            progress(256)
    return values.reshape(*grid.shape, 3, 3)


@register
class PolyFit(Fitter):
    """Himberg 2010's local polynomial fit as a :class:`~ivc.lut.fitter.Fitter` (a grid method: it fits
    the table's nodes, so :meth:`fit` needs the grid).

    ``degree``: of the polynomial in each neighbourhood (None: the default, 2); ``radius``: the neighbourhood, m
    (default: the grid's spacing). Fitted attributes: ``grid_``, ``values_`` (nx, ny, nz, 3, 3; NaN at
    the nodes too thinly surrounded to fit), ``radius_`` and ``report_``. :meth:`predict` interpolates
    the fitted nodes as a table does (Catmull-Rom), NaN where a needed node is unfitted or outside the
    grid; its cross-validation refits the grid without each fold.
    """

    name = "poly"

    def __init__(self, degree: int | None = None, radius: float | None = None, cv: BlockedKFold | None = None):
        if degree is not None and (not isinstance(degree, int | np.integer) or degree < 1):
            raise InputError(f"polynomial degree must be a whole number of at least 1, got {degree!r}")
        if radius is not None and not (np.isfinite(radius) and radius > 0):
            raise InputError(f"radius must be a positive number of metres, got {radius}")
        self.degree = degree
        self.radius = radius
        self.cv = BlockedKFold() if cv is None else cv

    def fit(self, samples: FieldSamples, grid: Grid | None = None,
            progress: Callable[[int], None] | None = None) -> PolyFit:
        if grid is None:
            raise InputError("the poly fit fits the nodes of a grid: call fit(samples, grid)")
        radius = grid.spacing if self.radius is None else self.radius
        degree = DEFAULT_DEGREE if self.degree is None else self.degree
        self.values_ = fit_poly(samples, grid, degree, radius, progress=progress)
        self.grid_, self.radius_ = grid, radius
        self._field = GridField(grid, self.values_, np.ones(grid.shape, bool))  # drops the unfitted (NaN) nodes
        self.report_ = {"degree": degree, "degree_chosen_by": "default" if self.degree is None else "user",
                        "radius_mm": 1000 * radius}
        return self

    def predict(self, positions: np.ndarray) -> np.ndarray:
        self._check_fitted("values_")
        positions = np.asarray(positions, float)
        g, _, mapped = self._field.evaluate(positions.reshape(-1, 3))
        g[~mapped] = np.nan
        return g.reshape(*positions.shape[:-1], 3, 3)

    def tabulate(self, grid: Grid) -> np.ndarray:
        """The fitted node values (``grid`` must be the grid of the fit)."""
        self._check_fitted("values_")
        same = (grid.shape == self.grid_.shape and grid.spacing == self.grid_.spacing
                and np.array_equal(grid.origin, self.grid_.origin))
        if not same:
            raise InputError("the poly fit tabulates the grid it was fitted on; fit it again for another grid")
        return self.values_
