"""The secondary field of a scene: eddy currents in conductors plus induced ferrous dipoles.

``SecondaryField(points)`` returns ``G`` (..., 3, 3) in the units of ``ivc.dipole``
(source frame; column j for source coil j). Inside a declared region of interest the
eddy-current part is tabulated once on a regular grid and interpolated with cubic
splines (the direct sum over thousands of triangle dipoles costs ~30 µs a point);
outside it, it is summed directly. The same point always gets the same value.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ivc import dipole
from ivc.sim.eddy import FaceDipoles


@dataclass
class FerrousSphere:
    """A soft-magnetic sphere: in the primary field it becomes an induced dipole.

    ``m = 4π a³ (μr − 1)/(μr + 2) H0``, i.e. in normalised units its field at ``x`` is
    ``a³ K f_D(x − c) f_D(c)`` with ``K = (μr − 1)/(μr + 2)``. Interaction with the
    conductors' eddy currents is neglected.
    """

    position: np.ndarray  # (3,) metres
    radius: float  # metres
    permeability: float  # relative

    def field(self, points: np.ndarray) -> np.ndarray:
        k = (self.permeability - 1.0) / (self.permeability + 2.0)
        return self.radius**3 * k * dipole.field(np.asarray(points) - self.position) @ dipole.field(self.position)


@dataclass
class SecondaryField:
    """G(r) of a scene. ``roi`` = (lower corner, upper corner) in metres, tabulated at ``spacing``."""

    dipoles: FaceDipoles | None = None
    spheres: list[FerrousSphere] = field(default_factory=list)
    roi: tuple[np.ndarray, np.ndarray] | None = None
    spacing: float = 0.01
    _coefficients: np.ndarray | None = field(default=None, repr=False)
    _origin: np.ndarray | None = field(default=None, repr=False)

    def exact(self, points) -> np.ndarray:
        """G by direct summation (no tabulation)."""
        points = np.asarray(points, float)
        G = np.zeros(points.shape[:-1] + (3, 3))
        if self.dipoles is not None:
            G += self.dipoles.field(points)
        for sphere in self.spheres:
            G += sphere.field(points)
        return G

    def tabulate(self, progress=None) -> None:
        """Tabulate the eddy-current part on the region-of-interest grid (done once).

        ``progress(done, total)`` is called after each slab of the grid.
        """
        if self.dipoles is None or self.roi is None or self._coefficients is not None:
            return
        lower, upper = (np.asarray(c, float) for c in self.roi)
        # two extra nodes each side so the cubic spline is accurate up to the ROI's faces
        origin = lower - 2 * self.spacing
        shape = np.ceil((upper - lower) / self.spacing).astype(int) + 5
        axes = [origin[i] + self.spacing * np.arange(shape[i]) for i in range(3)]
        nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
        values = np.empty(tuple(shape) + (3, 3))
        for i in range(shape[0]):  # one slab at a time, so progress can be shown
            values[i] = self.dipoles.field(nodes[i])
            if progress is not None:
                progress(i + 1, shape[0])
        self._coefficients = np.stack(
            [ndimage.spline_filter(values[..., a, b], order=3, mode="nearest") for a in range(3) for b in range(3)]
        )
        self._origin = origin

    def __call__(self, points) -> np.ndarray:
        points = np.asarray(points, float)
        flat = points.reshape(-1, 3)
        if self.dipoles is None or self.roi is None:
            return self.exact(points)
        self.tabulate()
        G = np.empty((len(flat), 3, 3))
        lower, upper = self.roi
        inside = np.all((flat >= lower) & (flat <= upper), axis=1)
        coords = ((flat[inside] - self._origin) / self.spacing).T
        for c in range(9):
            G[inside, c // 3, c % 3] = ndimage.map_coordinates(
                self._coefficients[c], coords, order=3, mode="nearest", prefilter=False
            )
        if np.any(~inside):
            G[~inside] = self.dipoles.field(flat[~inside])
        for sphere in self.spheres:
            G += sphere.field(flat)
        return G.reshape(points.shape[:-1] + (3, 3))
