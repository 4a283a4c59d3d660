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

from ivc.lut.grid import Grid
from ivc.lut.samples import FieldSamples

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
