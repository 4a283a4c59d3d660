"""Where a cold correction starts: the correction ``r − v`` tabulated at the closed-form dipole position v.

``B = SᵀS = MᵀM`` does not depend on the sensor's orientation (``S = Tᵀ M``, ``T`` a rotation), so
the closed-form dipole position of a frame (docs/math.md §3) is a function of the true position
alone, ``v = φ(r)``, with ``φ`` the closed form applied to ``M = f_D + g`` (the pose-domain map of
``ivc.correct.reported``). Tabulating ``φ⁻¹(v) − v`` on a grid in ``v`` once per table turns
a cold start into one closed-form position and one 3-channel look-up: on the default scene's check
poses the start lands a median 4 µm from the converged answer (the fixed point of two more closed
forms: a fraction of a millimetre), leaving two to three Gauss-Newton iterations.

The nodes are those of the table's grid grown by ``margin`` cells on every face and refined
``subdivision`` times (not refined where that would exceed :data:`MAX_NODES`); each is inverted by the
pose path's compiled Broyden solve (:func:`ivc.correct.reported_kernels.invert_kernel`) from the node
itself. A node counts when the inversion converged and its image is finite; frames whose ``v``
lies in a cell with an uncounted corner start from the fixed point as before, so the map only
changes where a frame starts, never which answer is accepted (each start still ends in the same
Levenberg-Marquardt run with the same stopping rule).
"""

from __future__ import annotations

import numpy as np

from ivc.table.grid import Grid, GridField

#: map nodes per table cell edge (1 where that would give more than MAX_NODES nodes)
SUBDIVISION = 2
MAX_NODES = 60_000
#: table cells the map extends beyond the table's box on every face (a frame just inside the mapped
#: volume can have its closed-form position outside the box)
MARGIN = 1
#: the inversion of a node stops when it reproduces the node to this (m)
TOLERANCE = 1e-11
MAX_ITERATIONS = 40


def correction_seeds(field: GridField, hemisphere: np.ndarray, subdivision: int = SUBDIVISION,
                     margin: int = MARGIN) -> GridField:
    """The map ``v ↦ φ⁻¹(v) − v`` (m) of the table ``field`` as a 3-channel cubic :class:`GridField` over the
    table's box; ``hemisphere`` is the unit vector of ``ivc.dipole.pose.hemisphere_vector``."""
    from ivc import compiled
    from ivc.correct import reported_kernels as pose_kernels

    base = field.grid
    if np.prod((np.array(base.shape) - 1 + 2 * margin) * subdivision + 1) > MAX_NODES:
        subdivision = 1
    grid = Grid(base.origin - margin * base.spacing, base.spacing / subdivision,
                tuple((np.array(base.shape) - 1 + 2 * margin) * subdivision + 1))
    v = np.ascontiguousarray(grid.nodes().reshape(-1, 3))
    n = len(v)
    H = np.ascontiguousarray(np.broadcast_to(np.eye(3), (n, 3, 3)))
    r, C = np.empty((n, 3)), np.empty((n, 3, 3))
    miss, converged = np.empty(n), np.empty(n, dtype=bool)
    iterations, mapped = np.empty(n, dtype=np.int64), np.empty(n, dtype=bool)
    kernel = compiled.choose(pose_kernels.invert_kernel, n)
    limits = pose_kernels.Limits(int(MAX_ITERATIONS), float(TOLERANCE), 0)
    none = np.full((n, 3), np.nan)  # no solution known: every node is solved to convergence
    kernel(v, v.copy(), H, none, np.ascontiguousarray(hemisphere, dtype=float), field.kernel_grid, tuple(limits), r, C,
           (miss, converged, iterations, mapped))  # an InvertOutput
    good = converged & np.all(np.isfinite(r), axis=1) & (miss <= TOLERANCE)
    delta = np.where(good[:, None], r - v, 0.0)
    return GridField(grid, delta.reshape(*grid.shape, 3), good.reshape(grid.shape), "cubic")
