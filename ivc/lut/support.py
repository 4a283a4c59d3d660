"""How well the data support each grid node, and which nodes are valid (docs/math.md §8)."""

from __future__ import annotations

import numpy as np

from ivc.table.grid import Grid

#: samples needed around a node (in its eight cells) for it to count as mapped
MIN_SUPPORT = 20


def node_support(grid: Grid, positions: np.ndarray) -> np.ndarray:
    """Samples in the (up to) eight cells around each node (nx, ny, nz) int."""
    cell = np.floor((np.asarray(positions, float) - grid.origin) / grid.spacing).astype(np.int64)
    cells = np.array(grid.shape) - 1
    inside = np.all((cell >= 0) & (cell < cells), axis=1)
    flat = np.ravel_multi_index(tuple(cell[inside].T), tuple(cells))
    counts = np.bincount(flat, minlength=int(np.prod(cells))).reshape(tuple(cells))
    padded = np.pad(counts, 1)
    support = np.zeros(grid.shape, dtype=np.int64)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                support += padded[dx : dx + grid.shape[0], dy : dy + grid.shape[1], dz : dz + grid.shape[2]]
    return support


def mapped_nodes(values: np.ndarray, support: np.ndarray, min_support: int) -> np.ndarray:
    """Nodes (nx, ny, nz) with at least ``min_support`` samples around them and a fitted (finite) value."""
    return (support >= min_support) & np.all(np.isfinite(values.reshape(*support.shape, 9)), axis=-1)
