"""How much of a declared working volume (an axis-aligned box) a look-up table maps."""

from __future__ import annotations

import numpy as np

from ivc.fixtures.volume import STEP, box_points, face_shares
from ivc.table.grid import GridField

__all__ = ["STEP", "box_coverage", "box_points"]


def box_coverage(field: GridField, center: np.ndarray, size: np.ndarray, step: float = STEP) -> dict:
    """The share of the box (``center``, ``size`` m, source frame) inside the table's mapped volume (cells whose
    eight nodes are valid), probed on a lattice of ``step`` m: ``fraction`` (0-1), ``mapped_litres`` of the box,
    ``box_litres`` and, per face, the mapped share of the layer within 5 cm of it (``faces``: -x, +x, -y, …)."""
    points = box_points(center, size, step)
    mapped = field.mapped(points)
    center, size = np.asarray(center, float).reshape(3), np.asarray(size, float).reshape(3)
    faces = face_shares(points, mapped, center, size)
    litres = float(np.prod(size) * 1000)
    return {"fraction": float(mapped.mean()), "mapped_litres": float(mapped.mean() * litres), "box_litres": litres,
            "center_m": center.tolist(), "size_m": size.tolist(), "faces": faces}
