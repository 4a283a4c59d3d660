"""The regular grid of a look-up table and the field interpolated on it (docs/math.md §8).

Nodes are ``origin + spacing · (i, j, k)``, ``i < nx`` etc., metres in the source frame.
Flattened node order is Himberg 2010's (eq. 105): X slowest, Z fastest, ``Δ = i·ny·nz + j·nz + k``,
which is NumPy's C order of an ``(nx, ny, nz)`` array.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ivc import compiled
from ivc.errors import InputError
from ivc.table import grid_numpy
from ivc.table import kernels as _kernels

#: Himberg 2010's grid spacing (1.5 inch), metres
DEFAULT_SPACING = 0.0381
INTERPOLATIONS = ("cubic", "linear")


@dataclass(frozen=True)
class Grid:
    """``origin`` (3,) metres (minimum corner), isotropic ``spacing`` metres, ``shape`` (nx, ny, nz)."""

    origin: np.ndarray
    spacing: float
    shape: tuple[int, int, int]

    def __post_init__(self):
        if np.asarray(self.origin).dtype.kind not in "biuf":
            raise InputError(f"grid origin must be three real numbers, got {self.origin!r}")
        object.__setattr__(self, "origin", np.asarray(self.origin, float).reshape(3))
        object.__setattr__(self, "shape", tuple(int(n) for n in self.shape))
        if not self.spacing > 0 or not np.isfinite(self.spacing):
            raise InputError(f"grid spacing must be positive, got {self.spacing}")
        if len(self.shape) != 3 or min(self.shape) < 2:
            raise InputError(f"a grid needs at least 2 nodes per axis, got shape {self.shape}")
        if not np.all(np.isfinite(self.origin)):
            raise InputError(f"grid origin must be finite, got {self.origin}")

    @classmethod
    def around(cls, points: np.ndarray, spacing: float = DEFAULT_SPACING, margin: int = 1) -> Grid:
        """The grid covering a cloud of points (N, 3), centred on it, grown by ``margin`` cells on every face."""
        points = np.asarray(points, float)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
            raise InputError(f"need a non-empty (N, 3) point cloud to place a grid, got shape {points.shape}")
        low, high = points.min(axis=0), points.max(axis=0)
        cells = np.maximum(np.ceil((high - low) / spacing - 1e-9).astype(int), 1)
        slack = cells * spacing - (high - low)
        origin = low - slack / 2 - margin * spacing
        return cls(origin, float(spacing), tuple(cells + 1 + 2 * margin))

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def nodes(self) -> np.ndarray:
        """Node positions (nx, ny, nz, 3), metres."""
        axes = [self.origin[a] + self.spacing * np.arange(self.shape[a]) for a in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    def flat_index(self, i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Himberg 2010, eq. 105: ``Δ(α, γ) = α_0 γ_1 γ_2 + α_1 γ_2 + α_2``."""
        return (np.asarray(i) * self.shape[1] + np.asarray(j)) * self.shape[2] + np.asarray(k)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """True where points (..., 3) lie within the grid's box."""
        u = (np.asarray(points, float) - self.origin) / self.spacing
        return np.all((u >= 0) & (u <= np.array(self.shape) - 1), axis=-1)


def fill_invalid(values: np.ndarray, valid: np.ndarray, pad: int = 1) -> np.ndarray:
    """``values`` (nx, ny, nz, C) padded by ``pad`` ghost nodes per face, with every invalid or ghost node
    filled by linear extrapolation from its valid neighbours (nearest value where only one is known).

    Only used so that the interpolation stencil of a valid cell is defined; cells touching
    such nodes are flagged by the caller, never silently trusted.
    """
    nx, ny, nz, C = values.shape
    out = np.zeros((nx + 2 * pad, ny + 2 * pad, nz + 2 * pad, C))
    known = np.zeros(out.shape[:3], dtype=bool)
    inner = (slice(pad, pad + nx), slice(pad, pad + ny), slice(pad, pad + nz))
    out[inner] = np.where(valid[..., None], values, 0.0)
    known[inner] = valid
    if not known.any():
        raise InputError("the table has no valid node to fill from")
    while not known.all():
        total = np.zeros_like(out)
        count = np.zeros(known.shape)
        for axis in range(3):
            for direction in (1, -1):
                n1 = np.roll(known, direction, axis)  # neighbour one step back along -direction
                n2 = np.roll(known, 2 * direction, axis)
                v1 = np.roll(out, direction, axis)
                v2 = np.roll(out, 2 * direction, axis)
                edge = _wrapped(known.shape, axis, direction)
                n1 &= ~edge[0]
                n2 &= ~edge[1]
                linear = n1 & n2
                total += np.where(linear[..., None], 2 * v1 - v2, np.where(n1[..., None], v1, 0.0))
                count += n1
        new = ~known & (count > 0)
        out[new] = total[new] / count[new, None]
        known |= new
    return out


def _wrapped(shape, axis, direction):
    """Masks of the positions where np.roll by ``direction`` and ``2 * direction`` wrapped around."""
    index = np.arange(shape[axis])
    if direction > 0:
        w1, w2 = index < 1, index < 2
    else:
        w1, w2 = index >= shape[axis] - 1, index >= shape[axis] - 2
    view = [1, 1, 1]
    view[axis] = shape[axis]
    return np.broadcast_to(w1.reshape(view), shape), np.broadcast_to(w2.reshape(view), shape)


class GridField:
    """A 3x3 field tabulated on a grid: ``g(r)``, ``∂g/∂r`` and whether ``r`` is in the mapped volume.

    ``values`` (nx, ny, nz, 3, 3); ``valid`` (nx, ny, nz) bool. A point is *mapped* when it
    lies in a cell whose eight corner nodes are all valid. ``interpolation``: ``cubic``
    (Catmull-Rom, C1, the default) or ``linear`` (trilinear, Himberg 2010's). Outside the grid the
    value of the nearest boundary point is returned and the point is flagged unmapped.
    """

    def __init__(self, grid: Grid, values: np.ndarray, valid: np.ndarray, interpolation: str = "cubic"):
        if interpolation not in INTERPOLATIONS:
            raise InputError(f"unknown interpolation {interpolation!r}; use one of {', '.join(INTERPOLATIONS)}")
        values = np.asarray(values, float)
        valid = np.asarray(valid, bool) & np.all(np.isfinite(values.reshape(*grid.shape, -1)), axis=-1)
        if values.shape[:3] != grid.shape or valid.shape != grid.shape:
            raise InputError(f"table shape {values.shape[:3]} / validity {valid.shape} do not match grid {grid.shape}")
        self.grid, self.interpolation = grid, interpolation
        self.channel_shape = values.shape[3:]
        self._padded = np.ascontiguousarray(fill_invalid(values.reshape(*grid.shape, -1), valid))
        v = valid
        self.valid_cells = np.ascontiguousarray(
            v[:-1, :-1, :-1] & v[1:, :-1, :-1] & v[:-1, 1:, :-1] & v[:-1, :-1, 1:]
            & v[1:, 1:, :-1] & v[1:, :-1, 1:] & v[:-1, 1:, 1:] & v[1:, 1:, 1:])
        self._origin = np.ascontiguousarray(grid.origin)
        self._shape = np.array(grid.shape, dtype=np.int64)

    @property
    def kernel_grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray, bool]:
        """The table as compiled look-ups take it: padded values (nx+2, ny+2, nz+2, C), valid cells
        (nx-1, ny-1, nz-1), origin (3,) m, spacing m, shape (3,) int64 and whether the interpolation is cubic."""
        return (self._padded, self.valid_cells, self._origin, float(self.grid.spacing), self._shape,
                self.interpolation == "cubic")

    def evaluate(self, r: np.ndarray, parallel: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(g (..., *channels), ∂g/∂r (..., *channels, 3), mapped (...))`` at points r (..., 3), metres.
        ``parallel`` False: the NumPy form (equal to rounding), for a few points, where starting the parallel
        kernel's threads costs more than the work (milliseconds on a loaded machine)."""
        r = np.asarray(r, float)
        lead = r.shape[:-1]
        points = np.ascontiguousarray(r.reshape(-1, 3))
        C = self._padded.shape[3]
        values = np.empty((len(points), C))
        gradients = np.empty((len(points), C, 3))
        mapped = np.empty(len(points), dtype=bool)
        kernel = (compiled.choose(_kernels.grid_kernel, len(points), compiled.VECTORISED, grid_numpy.grid_kernel)
                  if parallel else grid_numpy.grid_kernel)
        kernel(self.kernel_grid, points, values, gradients, mapped)
        finite = np.all(np.isfinite(points), axis=1)
        mapped &= finite
        return (values.reshape(*lead, *self.channel_shape), gradients.reshape(*lead, *self.channel_shape, 3),
                mapped.reshape(lead))

    def __call__(self, r: np.ndarray) -> np.ndarray:
        return self.evaluate(r)[0]

    def value_and_jacobian(self, r: np.ndarray, parallel: bool = True) -> tuple[np.ndarray, np.ndarray]:
        g, dg, _ = self.evaluate(r, parallel)
        return g, dg

    def mapped(self, r: np.ndarray) -> np.ndarray:
        return self.evaluate(r)[2]
