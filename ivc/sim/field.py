"""The secondary field of a scene: eddy currents in conductors plus induced ferrous dipoles.

``SecondaryField(points)`` returns ``G`` (..., 3, 3) in the units of ``ivc.dipole``
(source frame; column j for source coil j). Inside a declared region of interest the
eddy-current part is tabulated once on a regular grid and interpolated with cubic
splines (the direct sum over thousands of triangle dipoles costs ~30 µs a point);
outside it, it is summed directly. The same point always gets the same value.

With ``IVC_FIELD_CACHE`` set to a folder, a tabulation is kept there, named by a hash of everything it
depends on (the face dipoles, the region, the spacing), and the next tabulation of the same field loads it
instead of summing again (the same bytes: tabulating is deterministic). The test suite sets it to one folder
per run, shared by its processes, because the same scenes are simulated in many test modules.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from ivc import dipole
from ivc.sim.eddy import FaceDipoles


@dataclass
class FerrousSphere:
    """A soft-magnetic sphere: in the primary field it becomes an induced dipole.

    ``m = 4π a³ (μr − 1)/(μr + 2) H0``, i.e. in normalised units its field at ``x`` is
    ``a³ K f_D(x − c) f_D(c)`` with ``K = (μr − 1)/(μr + 2)``. Interaction with the
    conductors' eddy currents is neglected. ``gain`` multiplies the induced moment (1: the physical sphere; a
    scene's ``induced_scale`` sets it).
    """

    position: np.ndarray  # (3,) metres
    radius: float  # metres
    permeability: float  # relative
    gain: float = 1.0

    def field(self, points: np.ndarray) -> np.ndarray:
        k = self.gain * (self.permeability - 1.0) / (self.permeability + 2.0)
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
        cached = _cache_file(self.dipoles, lower, upper, self.spacing)
        if cached is not None and cached.exists():
            self._coefficients = np.load(cached, allow_pickle=False)
            self._origin = origin
            if progress is not None:
                progress(shape[0], shape[0])
            return
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
        if cached is not None:
            _store(cached, self._coefficients)

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


CACHE_VARIABLE = "IVC_FIELD_CACHE"


def _cache_file(dipoles: FaceDipoles, lower: np.ndarray, upper: np.ndarray, spacing: float) -> Path | None:
    """Where the tabulation of these dipoles over [lower, upper] at ``spacing`` is kept (``IVC_FIELD_CACHE``),
    or None when no folder is set."""
    folder = os.environ.get(CACHE_VARIABLE)
    if not folder:
        return None
    digest = hashlib.sha256(b"ivc-secondary-field-1")
    for a in (dipoles.centres, dipoles.moments, lower, upper, np.array([spacing])):
        a = np.ascontiguousarray(a, dtype=float)
        digest.update(str(a.shape).encode())
        digest.update(a.tobytes())
    return Path(folder) / f"field-{digest.hexdigest()[:32]}.npy"


def _store(path: Path, coefficients: np.ndarray) -> None:
    """Write ``coefficients`` to ``path`` atomically (a reader sees the whole file or none); a folder that
    cannot be written only costs the next run the tabulation."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".tmp", delete=False) as f:
            np.save(f, coefficients, allow_pickle=False)
        os.replace(f.name, path)
    except OSError:
        pass
