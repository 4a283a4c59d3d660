"""How much of a declared working volume (an axis-aligned box) a look-up table maps."""

from __future__ import annotations

import numpy as np

from ivc.errors import InputError
from ivc.table.grid import GridField

#: lattice step (m) at which the box is probed
STEP = 0.01


def box_points(center: np.ndarray, size: np.ndarray, step: float = STEP) -> np.ndarray:
    """Cell centres (N, 3) m of a lattice of ``step`` filling the box of ``center`` (3,) and ``size`` (3,) m."""
    center, size = np.asarray(center, float).reshape(-1), np.asarray(size, float).reshape(-1)
    if center.shape != (3,) or size.shape != (3,) or not np.all(size > 0) or not np.all(np.isfinite(center)):
        raise InputError(f"a box needs a finite centre (3,) and positive sizes (3,) in metres, got {center} and {size}")
    if not (np.isfinite(step) and step > 0):
        raise InputError(f"the lattice step must be a positive number of metres, got {step}")
    low = center - size / 2
    counts = np.maximum(np.round(size / step).astype(int), 1)
    axes = [low[a] + (np.arange(counts[a]) + 0.5) * size[a] / counts[a] for a in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def box_coverage(field: GridField, center: np.ndarray, size: np.ndarray, step: float = STEP) -> dict:
    """The share of the box (``center``, ``size`` m, source frame) inside the table's mapped volume (cells whose
    eight nodes are valid), probed on a lattice of ``step`` m: ``fraction`` (0-1), ``mapped_litres`` of the box,
    ``box_litres`` and, per face, the mapped share of the layer within 5 cm of it (``faces``: -x, +x, -y, …)."""
    points = box_points(center, size, step)
    mapped = field.mapped(points)
    center, size = np.asarray(center, float).reshape(3), np.asarray(size, float).reshape(3)
    low, high = center - size / 2, center + size / 2
    faces = {}
    for axis, name in enumerate("xyz"):
        for sign, near in (("-", points[:, axis] - low[axis] < 0.05), ("+", high[axis] - points[:, axis] < 0.05)):
            faces[f"{sign}{name}"] = float(mapped[near].mean()) if near.any() else float("nan")
    litres = float(np.prod(size) * 1000)
    return {"fraction": float(mapped.mean()), "mapped_litres": float(mapped.mean() * litres), "box_litres": litres,
            "center_m": center.tolist(), "size_m": size.tolist(), "faces": faces}
