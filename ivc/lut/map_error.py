"""The table's own error, measured from its fit residuals: the part that revisits of one place share.

A sample's fit residual (what the sample measured minus what the table predicts there) is the table's
error at that place plus the sample's own noise. The tracker's noise is independent between two visits
of the same place at different times; the table's error is not: it is the same function of position for
both. So the mean product of the residuals of two samples in the same grid cell, recorded in different
time blocks, estimates the table's mean squared error there, free of the tracker's noise (the variogram's
nugget separated from its sill; Cressie 1993, section 2.3). Pairs from the same block are left out, since
consecutive frames share slow errors (the fixture's own pose error along the sweep) that are not the
table's.

The products are pooled over all cells into one figure: one cell holds too few independent visits to
estimate its own error (measured: the per-cell estimate, smoothed over 3-5 cells, moved the default
scene's prediction less than the pooled one and kept most of the severe scene's poses beyond 5x their
prediction). ``ivc.correct`` adds the pooled figure to the predicted precision in quadrature.
"""

from __future__ import annotations

import numpy as np

from ivc.errors import InputError
from ivc.table.grid import Grid

#: revisits count when they are at least this far apart in time (s): blocks of the sweep this long
BLOCK_SECONDS = 10.0


def shared_residual(position: np.ndarray, residual: np.ndarray, time: np.ndarray, grid: Grid,
                    block_seconds: float = BLOCK_SECONDS) -> float:
    """RMS length of the residual part shared by revisits (the residual's units; NaN with no revisit).

    ``position`` (N, 3) m: where each sample is, binned by ``grid``'s cells; ``residual`` (N, D): each
    sample's fit residual, any units; ``time`` (N,) s: when it was recorded. Two samples are revisits of
    one place when they share a cell and lie in different blocks of ``block_seconds``. Returns
    ``sqrt(max(0, mean over revisit pairs of r_i · r_j))``.
    """
    position = np.asarray(position, float)
    residual = np.asarray(residual, float)
    time = np.asarray(time, float)
    n = len(position)
    if position.shape != (n, 3) or residual.ndim != 2 or len(residual) != n or time.shape != (n,):
        raise InputError(f"shared_residual: position {position.shape}, residual {residual.shape} and time "
                         f"{time.shape} must be (N, 3), (N, D) and (N,)")
    if not block_seconds > 0:
        raise InputError(f"block_seconds must be positive, got {block_seconds}")
    keep = np.all(np.isfinite(position), axis=1) & np.all(np.isfinite(residual), axis=1) & np.isfinite(time)
    position, residual, time = position[keep], residual[keep], time[keep]
    if len(position) < 2:
        return float("nan")
    cell = np.floor((position - grid.origin) / grid.spacing).astype(np.int64)
    cell -= cell.min(axis=0)
    span = cell.max(axis=0) + 1
    cell_id = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
    block = np.floor((time - time.min()) / block_seconds).astype(np.int64)
    _, cell_index = np.unique(cell_id, return_inverse=True)
    _, part_index = np.unique(cell_id * (block.max() + 1) + block, return_inverse=True)
    # sum over pairs (i ≠ j) in one cell of r_i · r_j = |Σ r|² − Σ |r|²; minus the same within each block
    cell_sum = np.zeros((cell_index.max() + 1, residual.shape[1]))
    np.add.at(cell_sum, cell_index, residual)
    part_sum = np.zeros((part_index.max() + 1, residual.shape[1]))
    np.add.at(part_sum, part_index, residual)
    cell_count = np.bincount(cell_index).astype(float)
    part_count = np.bincount(part_index).astype(float)
    products = np.sum(cell_sum**2) - np.sum(part_sum**2)
    pairs = np.sum(cell_count**2) - np.sum(part_count**2)
    if pairs <= 0:
        return float("nan")
    return float(np.sqrt(max(products / pairs, 0.0)))
