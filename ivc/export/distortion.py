"""The room's distortion in the pose domain, on a grid: what a position-indexed correction table needs.

With the closed-form dipole solver, the reported position depends only on ``F = f_D(r) + G(r)``
(it comes from ``SᵀS = FᵀF``, which the sensor's rotation cancels), and the reported
orientation is the true one turned by a rotation ``C(r)`` on the left (``T' = C(r) T``). So the
distortion is a field of positions and rotations over the room, whatever the sensors' attitude:

* :func:`forward`: true node position → reported position and ``C``, straight from the
  table's node values (no interpolation, no solve other than the dipole's);
* :func:`correction`: reported position on the table's grid → true position and ``Cᵀ``, by
  inverting the forward map through the table's interpolant;
* :func:`reported_correction`: the same on a grid spanning where the tracker *reports* the
  mapped volume (what a consumer of reported poses needs: the table's own grid covers the true
  positions), inverted by :class:`ivc.correct.reported.PoseCorrector`, the inversion
  ``ivc correct`` applies to reported poses.

Positions in metres in the table's source frame; rotations as (..., 3, 3) matrices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ivc import dipole, rotations
from ivc.dipole.pose import closed_form_pose
from ivc.errors import ExportError
from ivc.table.grid import Grid, GridField
from ivc.table.lookup import LookupTable

#: default node spacing of a grid over the reported region: the table's spacing divided by this
REPORTED_SUBDIVISION = 4
#: nodes at most in a grid over the reported region (about 100 MB of correction arrays)
MAX_REPORTED_NODES = 4_000_000


@dataclass
class DistortionGrid:
    """Per node of a grid (nx, ny, nz): ``source`` node positions (…, 3) m, the ``target`` positions they
    map to (…, 3) m, the rotation ``turn`` (…, 3, 3) applied on the left of the orientation, and ``valid``
    (…) bool; invalid nodes hold NaN. ``grid``: the nodes' grid (the table's, or one over the reported
    region). ``extension`` (…, 3) m, from :func:`reported_correction` only: at invalid nodes, a true
    position that reproduces the node all the same (just past the mapped volume, or found from another
    start), else NaN."""

    source: np.ndarray
    target: np.ndarray
    turn: np.ndarray
    valid: np.ndarray
    grid: Grid | None = None
    extension: np.ndarray | None = None

    @property
    def displacement(self) -> np.ndarray:
        """target − source (…, 3) m, zero at invalid nodes."""
        return np.where(self.valid[..., None], self.target - self.source, 0.0)

    @property
    def rotation_vector(self) -> np.ndarray:
        """``turn`` as axis × angle (…, 3) rad, zero at invalid nodes."""
        rv = rotations.to_rotvec(rotations.from_matrix(np.where(self.valid[..., None, None], self.turn, np.eye(3))))
        return np.where(self.valid[..., None], rv, 0.0)

    def defined_at(self, points: np.ndarray) -> np.ndarray:
        """True where points (..., 3) m lie in a cell of :attr:`grid` whose eight corners are valid: where an
        export interpolating between the nodes (ITK, Vrui) holds a defined correction."""
        g = self.grid
        u = (np.asarray(points, float) - g.origin) / g.spacing
        inside = np.all(np.isfinite(u) & (u >= 0) & (u <= np.array(g.shape) - 1), axis=-1)
        index = np.clip(np.floor(np.where(np.isfinite(u), u, 0)).astype(int), 0, np.array(g.shape) - 2)
        out = inside.copy()
        for corner in np.ndindex(2, 2, 2):
            k = index + np.array(corner)
            out &= self.valid[k[..., 0], k[..., 1], k[..., 2]]
        return out

    def filled_displacement(self) -> np.ndarray:
        """target − source (…, 3) m at valid nodes; at the others, what an export interpolating between
        nodes holds so that a cell touching them blends nearby corrections, never zero ("no correction"):
        the ``extension`` where there is one, else the displacement of the nearest node that has either."""
        shift = self.target - self.source
        if self.extension is not None:
            shift = np.where(self.valid[..., None], shift, self.extension - self.source)
        known = np.all(np.isfinite(shift), axis=-1)
        if not self.valid.any() or not known.any():
            raise ExportError("the correction is defined at no node of the grid: the table maps nothing a "
                              "tracker can report")
        nearest = ndimage.distance_transform_edt(~known, return_distances=False, return_indices=True)
        return shift[tuple(nearest)]


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
    return DistortionGrid(nodes, position, turn, valid, table.grid)


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
    return DistortionGrid(v, target, back, valid, table.grid)


def reported_region(table: LookupTable, spacing: float | None = None, solver: str | None = None,
                    margin: int = 1) -> Grid:
    """A grid (spacing m, default the table's / :data:`REPORTED_SUBDIVISION`) over where the tracker reports
    the table's mapped volume: the images ``φ(P)`` of probe points P filling the mapped cells, grown by
    ``margin`` cells on every face."""
    from ivc.correct.reported import PoseCorrector

    spacing = table.grid.spacing / REPORTED_SUBDIVISION if spacing is None else float(spacing)
    if not spacing > 0 or not np.isfinite(spacing):
        raise ExportError(f"grid spacing must be positive, got {spacing} m")
    images = PoseCorrector(table, solver=solver).seeds.images
    grid = Grid.around(images, spacing, margin)
    if grid.size > MAX_REPORTED_NODES:
        raise ExportError(f"a {spacing * 1000:g} mm grid over the reported region has {grid.size:,} nodes "
                          f"(at most {MAX_REPORTED_NODES:,}); choose a larger spacing")
    return grid


def reported_correction(table: LookupTable, spacing: float | None = None, solver: str | None = None,
                        progress=None) -> DistortionGrid:
    """Where a sensor reported at each node of :func:`reported_region` really is, and ``Cᵀ``.

    Each node is corrected as a reported pose by :class:`ivc.correct.reported.PoseCorrector` (the
    inversion ``ivc correct`` applies, with the tracker solver the table was fitted for unless
    ``solver`` names another). A node is valid where that correction is trusted (flags 0): the true
    position is inside the mapped volume and is the only one the map sends there. Invalid nodes hold
    NaN. ``extension`` holds, at invalid nodes, a true position that reproduces the node all the same:
    the correction's where it was flagged only OUTSIDE (just past the mapped volume), else an inversion
    from the nearest probe (:meth:`PoseCorrector.invert_from_probes`) where the one from the node failed.
    ``progress``: called with the number of nodes done (chunks of 65,536).
    """
    from ivc.correct.reported import PoseCorrector
    from ivc.correct.solver import NOT_CONVERGED, OUTSIDE

    grid = reported_region(table, spacing, solver)
    corrector = PoseCorrector(table, solver=solver)
    v = grid.nodes().reshape(-1, 3)
    target, turn = np.full((len(v), 3), np.nan), np.full((len(v), 3, 3), np.nan)
    valid = np.zeros(len(v), bool)
    extension = np.full((len(v), 3), np.nan)
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    chunk = 65_536
    for start in range(0, len(v), chunk):
        part = slice(start, start + chunk)
        out = corrector.batch(v[part], np.broadcast_to(identity, (len(v[part]), 4)))
        ok = out.flags == 0
        valid[part] = ok
        target[part][ok] = out.position[ok]
        outside = out.flags == OUTSIDE
        extension[part][outside] = out.position[outside]
        failed = np.flatnonzero(out.flags & NOT_CONVERGED)
        if len(failed):
            r, reproduced, _ = corrector.invert_from_probes(v[part][failed])
            extension[part][failed[reproduced]] = r[reproduced]
        turn[part][ok] = rotations.to_matrix(out.quaternion[ok])  # T = Cᵀ Q with Q = I
        if progress is not None:
            progress(len(v[part]))
    shape = grid.shape
    return DistortionGrid(v.reshape(*shape, 3), target.reshape(*shape, 3), turn.reshape(*shape, 3, 3),
                          valid.reshape(shape), grid, extension.reshape(*shape, 3))
