"""The room's distortion in the pose domain, on a grid: what a position-indexed correction table needs.

With the closed-form dipole solver, the reported position depends only on ``F = f_D(r) + G(r)``
(it comes from ``SᵀS = FᵀF``, which the sensor's rotation cancels), and the reported
orientation is the true one turned by a rotation ``C(r)`` on the left (``T' = C(r) T``). So the
distortion is a field of positions and rotations over the room, whatever the sensors' attitude:

* :func:`forward`: true node position → reported position and ``C``, straight from the
  table's node values (no interpolation, no solve other than the dipole's);
* :func:`correction`: reported position on a grid → true position and ``Cᵀ``, by inverting
  the forward map through the table's interpolant.

Positions in metres in the table's source frame; rotations as (..., 3, 3) matrices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ivc import dipole, rotations
from ivc.dipole.pose import closed_form_pose
from ivc.lut.grid import GridField
from ivc.lut.table import LookupTable


@dataclass
class DistortionGrid:
    """Per node of the table's grid (nx, ny, nz): ``source`` node positions (…, 3) m, the ``target``
    positions they map to (…, 3) m, the rotation ``turn`` (…, 3, 3) applied on the left of the
    orientation, and ``valid`` (…) bool. Invalid nodes hold NaN."""

    source: np.ndarray
    target: np.ndarray
    turn: np.ndarray
    valid: np.ndarray

    @property
    def displacement(self) -> np.ndarray:
        """target − source (…, 3) m, zero at invalid nodes."""
        return np.where(self.valid[..., None], self.target - self.source, 0.0)

    @property
    def rotation_vector(self) -> np.ndarray:
        """``turn`` as axis × angle (…, 3) rad, zero at invalid nodes."""
        rv = rotations.to_rotvec(rotations.from_matrix(np.where(self.valid[..., None, None], self.turn, np.eye(3))))
        return np.where(self.valid[..., None], rv, 0.0)


def reported(field: GridField, r: np.ndarray, hemisphere: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(reported position (…, 3), left rotation C (…, 3, 3), mapped (…)) of sensors at true positions r."""
    g, _, mapped = field.evaluate(r)
    position, turn = closed_form_pose(dipole.field(r) + g, hemisphere)
    return position, turn, mapped


def forward(table: LookupTable) -> DistortionGrid:
    """Where the tracker reports a sensor placed at each node (the distortion, true → reported).

    Straight from the node values: no interpolation.
    """
    nodes = table.grid.nodes()
    position, turn = closed_form_pose(dipole.field(nodes) + table.values, table.hemisphere)
    valid = table.valid & np.all(np.isfinite(position), axis=-1)
    position[~valid] = np.nan
    turn[~valid] = np.nan
    return DistortionGrid(nodes, position, turn, valid)


def correction(table: LookupTable, tolerance: float = 1e-9, max_iterations: int = 50,
               interpolation: str = "cubic") -> DistortionGrid:
    """Where a sensor reported at each node really is (the correction, reported → true), and ``Cᵀ``.

    Inverts :func:`reported` by the fixed-point iteration ``r ← r + (v − reported(r))`` (the
    distortion's gradient is far below 1, so it contracts). A node is valid when the iteration
    converges to ``tolerance`` (m) at a true position inside the mapped volume.
    """
    field = table.field(interpolation)
    v = table.grid.nodes()
    r = v.copy()
    for _ in range(max_iterations):
        position, turn, mapped = reported(field, r, table.hemisphere)
        miss = v - position
        r = r + miss
        if not np.nanmax(np.abs(miss), initial=0.0) > tolerance:
            break
    position, turn, mapped = reported(field, r, table.hemisphere)
    valid = mapped & (np.linalg.norm(v - position, axis=-1) <= 10 * tolerance)
    target = np.where(valid[..., None], r, np.nan)
    back = np.where(valid[..., None, None], np.swapaxes(turn, -1, -2), np.nan)
    return DistortionGrid(v, target, back, valid)
