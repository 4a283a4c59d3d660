"""How a look-up table is fitted: :class:`FitOptions`, the grid's memory check and the fit's limits.

Every fit path (:func:`ivc.lut.fit_lut` and the paths it chooses: the single sweep, the joint solve of
extension sweeps, reported poses) reads its options from here, so none of them imports another.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields

import numpy as np

from ivc.errors import InputError
from ivc.fixtures.mapping import Gates
from ivc.lut.fitter import FITTERS, Fitter, make_fitter
from ivc.lut.support import MIN_SUPPORT
from ivc.table.grid import DEFAULT_SPACING

make_fitter("harmonic")  # registers the built-in fitters
#: the fit methods (:data:`ivc.lut.fitter.FITTERS`' names)
METHODS = tuple(FITTERS)
#: fewest gated samples worth fitting, and the smallest fraction of the sweep that may pass the gates
MIN_SAMPLES = 2_000
MIN_KEPT_FRACTION = 0.05
#: coarsest grid spacing (m): an AC tracker's whole range is a few metres
MAX_SPACING = 1.0
#: estimated bytes per grid node at the peak of a fit: values and their padded, interpolated and refined
#: copies (9 float64 each), support, masks, node positions and the harmonic basis at the nodes
BYTES_PER_NODE = 2048
#: largest estimated grid memory a fit starts with (bytes)
MAX_GRID_MEMORY = 4 << 30

Progress = Callable[[str, int], Callable[[int], None]]


@dataclass
class FitOptions:
    """How :func:`fit_lut` builds a table.

    ``fitter``: a configured :class:`~ivc.lut.fitter.Fitter` (``HarmonicFit(degree=6)``,
    ``PolyFit(radius=0.05)``, ...) or a method name with its defaults (``METHODS``); it is
    copied, never fitted in place. ``spacing`` (m), ``origin``/``shape``: a user grid (else
    derived from the data, one-cell margin). ``refine``: re-solve the wand frames as rigid
    bodies against the map and refit (:func:`ivc.lut.refine.refine_map`), at most
    ``max_refinements`` times while it pays; on by default, as in ``ivc fit`` (docs/lut.md,
    "Refinement", says why). ``min_support``: samples around
    a node for it to count as mapped. ``max_residual``/``max_error`` (m): the sweep's gates.
    ``max_frames``: the sweep is decimated to at most this many frames (every k-th frame). At
    240 Hz consecutive frames are a fraction of a millimetre apart, so this loses no coverage;
    it bounds the time of the sweep solve, the fit and the refinement."""

    fitter: Fitter | str = "harmonic"
    spacing: float = DEFAULT_SPACING
    origin: tuple[float, float, float] | None = None
    shape: tuple[int, int, int] | None = None
    refine: bool = True
    max_refinements: int = 3
    min_support: int = MIN_SUPPORT
    max_residual: float = Gates.max_residual
    max_error: float = Gates.max_error
    max_frames: int = 25_000

    def __post_init__(self):
        self.fitter = make_fitter(self.fitter)
        if (self.origin is None) != (self.shape is None):
            raise InputError("a user grid needs both an origin and a shape")
        _check_range("max_refinements", self.max_refinements, 0)
        _check_range("max_frames", self.max_frames, 1)
        _check_range("min_support", self.min_support, 1)
        for name in ("max_residual", "max_error"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"{name} must be a positive number, got {value}")
        if not (np.isfinite(self.spacing) and 0 < self.spacing <= MAX_SPACING):
            raise InputError(f"grid spacing must be more than 0 and at most {1000 * MAX_SPACING:g} mm, got "
                             f"{1000 * self.spacing:g} mm")
        if self.shape is not None:
            check_grid_memory(tuple(self.shape))

    @property
    def method(self) -> str:
        """The fitter's method name."""
        return self.fitter.name

    def describe(self) -> dict:
        """The options as JSON-able values (the table's provenance ``parameters``): the fitter's
        configuration (:meth:`~ivc.lut.fitter.Fitter.describe`) beside the others."""
        others = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "fitter"}
        return {**self.fitter.describe(), **others}


def _check_range(name: str, value, low: int, high: int | None = None, optional: bool = False) -> None:
    if value is None and optional:
        return
    if not isinstance(value, int | np.integer) or value < low or (high is not None and value > high):
        span = f"at least {low}" if high is None else f"from {low} to {high}"
        raise InputError(f"{name} must be a whole number {span}, got {value!r}")


def grid_memory(shape: tuple[int, int, int]) -> int:
    """Estimated peak memory (bytes) of fitting, refining and interpolating a grid of ``shape`` nodes."""
    return int(np.prod(np.asarray(shape, dtype=float))) * BYTES_PER_NODE


def check_grid_memory(shape: tuple[int, int, int], limit: int | None = None) -> None:
    """Refuse, before any work, a grid whose estimated memory (:func:`grid_memory`) exceeds ``limit`` bytes
    (default MAX_GRID_MEMORY)."""
    limit = MAX_GRID_MEMORY if limit is None else limit
    if len(shape) != 3 or min(shape) < 2:
        raise InputError(f"a grid needs at least 2 nodes per axis, got shape {tuple(shape)}")
    need = grid_memory(shape)
    if need > limit:
        nodes = float(np.prod(np.asarray(shape, dtype=float)))
        raise InputError(f"a grid of {' x '.join(str(int(n)) for n in shape)} = {nodes:.3g} nodes needs about "
                         f"{need / 2**30:.3g} GiB (limit {limit / 2**30:.3g} GiB): use a coarser spacing "
                         "(spacing=SPACING) or fewer nodes")
