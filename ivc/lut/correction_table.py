"""The alternative to the physical map for pose-only trackers: a table of the correction itself.

A *pose-domain table* holds, on a grid over the **reported** positions, the correction
``d(v) = r − v`` (m) and the rotation vector ``w(v)`` of ``C(r)`` (rad), fitted to the wand's
(true pose, reported pose) pairs by Himberg 2010's local quadratic regression
(:func:`ivc.lut.fit_poly.fit_poly`, each node from the pairs within one spacing of it, all
octants required). Correcting is then an interpolation, no inversion:
``r = v + d(v)``, ``T = exp(−[w(v)]×) Q``.

It knows nothing of the physics (no harmonic constraint, no tracker model), and is kept to
measure the physically constrained table against (docs/lut.md, "Pose-only trackers").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ivc import rotations
from ivc.lut.fit_poly import fit_poly
from ivc.lut.samples import FieldSamples
from ivc.pose.reported_fit import PosePairs
from ivc.table.grid import DEFAULT_SPACING, Grid, GridField


@dataclass
class PoseDomainTable:
    """``field``: channels (displacement (3), rotation vector (3), zeros (3)) on a grid of reported positions."""

    field: GridField

    def correct(self, position: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True positions (n, 3) m, rotations (n, 3, 3) and ``mapped`` (n,) of reported poses (n, 3), (n, 3, 3)."""
        values, _, mapped = self.field.evaluate(np.where(np.isfinite(position), position, 0.0))
        with np.errstate(invalid="ignore"):
            turn = rotations.to_matrix(rotations.from_rotvec(values[:, 1]))
            return position + values[:, 0], np.swapaxes(turn, -1, -2) @ rotation, mapped & np.all(
                np.isfinite(position), axis=1)


def fit_pose_domain_table(pairs: PosePairs, spacing: float = DEFAULT_SPACING, degree: int = 2) -> PoseDomainTable:
    """Fit a :class:`PoseDomainTable` to pose pairs on a grid around their reported positions."""
    grid = Grid.around(pairs.reported_position, spacing)
    targets = np.zeros((len(pairs), 3, 3))
    targets[:, 0] = pairs.position - pairs.reported_position
    targets[:, 1] = rotations.to_rotvec(rotations.from_matrix(pairs.observed_turn))
    samples = FieldSamples(pairs.reported_position, targets, np.zeros(len(pairs)), pairs.frame, pairs.sensor)
    values = fit_poly(samples, grid, degree, spacing, weights=np.ones(len(pairs)))
    valid = np.all(np.isfinite(values.reshape(*grid.shape, 9)), axis=-1)
    return PoseDomainTable(GridField(grid, values, valid))
