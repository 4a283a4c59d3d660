"""Corrected poses from reported poses alone: the inverse of the tracker's pose-domain distortion.

A rotation-equivariant tracker reports ``v = φ(r)`` and ``Q = C(r) T`` for a sensor at ``(r, T)``,
with ``(φ, C)`` its solver applied to ``f_D + g`` (:mod:`ivc.pose.tracker_solver`). With the
table's ``g``, the correction ``r = φ⁻¹(v)``, ``T = C(r)ᵀ Q`` is exact: no signal is rebuilt and
no signal residual is asked for. Same :class:`~ivc.correct.solver.Correction` and flags as the
signal path, with these meanings:

``OUTSIDE``        the corrected position is outside the table's mapped volume
``NOT_CONVERGED``  the inversion did not reproduce the reported position to ``tolerance``
``HIGH_RESIDUAL``  the map does not produce the reported position, or not uniquely: the nearest
                   the inversion got, ``residual`` = |v − φ(r)| (m), is above ``max_residual``
                   (another room, a moved source, another hemisphere), or two distinct mapped
                   true positions produce it (see below)
``INVALID_INPUT``  the reported pose is not finite, or the sample was marked invalid
``LOW_PRECISION``  the pose's predicted precision is worse than the limit (:mod:`ivc.correct.precision`): the
                   tracker's noise on the reported pose, carried through the inverse map
                   (:func:`ivc.pose.precision.reported_pose_covariance`), which grows without bound where
                   the map folds

Where the inversion starts: at the reported position itself (a stream's sensor: moved by its
previous correction). Next to metal the map can send two distant true regions to the same
reported positions (measured on the default scene: about 0.2 % of the check poses), and pose-only
data cannot tell them apart. So each sample is also inverted (where anything shows a fold
near it: :data:`QUIET_SKIP`) from its nearest probe of a
:class:`SeedMap` (``φ`` and ``(∂φ/∂r)⁻¹`` tabulated at probe points over the mapped volume, the
table's grid refined twice), and from that probe's *partner* when its image lies among the
images of a distant region; when two starts give distinct mapped solutions the pose is
ambiguous and flagged HIGH_RESIDUAL (a reported pose the map does not produce uniquely). The
same holds for a solution in a *hole* of the map, an unmapped node of the grid where the table
still holds its model's values (:class:`HoleMap`): the truth may lie where no data mapped it. A
stream's continuing track skips that test: its history says which branch it is on.

For the closed-form tracker solver a compiled kernel does the inversion; for the
least-squares solver, :func:`ivc.pose.reported.invert_distortion` (NumPy) does.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy.spatial import cKDTree

from ivc import compiled, rotations
from ivc.correct import reported_kernels as _pose_kernels
from ivc.correct.precision import DEFAULT, PrecisionGate
from ivc.correct.solver import HIGH_RESIDUAL, INVALID_INPUT, Correction
from ivc.dipole.pose import hemisphere_vector
from ivc.errors import InputError
from ivc.pose.precision import reported_noise, reported_pose_covariance, traces
from ivc.pose.reported import invert_distortion
from ivc.pose.tracker_solver import check_solver, distortion
from ivc.table.grid import GridField
from ivc.table.lookup import LookupTable

#: the inversion stops when it reproduces the reported position to this (m)
TOLERANCE = 1e-11
#: HIGH_RESIDUAL above this miss of the reported position (m)
MAX_RESIDUAL_M = 1e-6
MAX_ITERATIONS = 40
#: two solutions farther apart than this (m) make a reported pose ambiguous
AMBIGUITY = 1e-3
#: a tracked sensor whose correction offset r − v moves more than this (m) between two of its samples is not
#: continuing its track (the map's other branch, or a gap): that sample is tested as if it started a track
TRACK_JUMP = 0.01
#: a failed inversion is restarted from the probe nearest in image where none of this many probes nearest in image
#: lies where the map folds (measured on the strong scene, 10,000 check poses: 47.6 % trusted without the restart,
#: 56.0 % with it, none more than 0.77 mm off; 27 probes: 52.8 %, 2: 57.9 %, on 1,955 others)
NEAR_PROBES = 8
#: probes per table cell edge
SUBDIVISION = 2
#: another mapped solution counts when it reproduces the reported position to this many times the reported
#: position's predicted RMS noise (a 3-D Gaussian is that far off with probability about 2e-10)
RIVAL_NOISE = 4.0
#: rival starts tried per sample (the probes nearest in image)
RIVALS = 4
#: the regions rival probes are picked from: blocks of this many probe spacings
REGION = 3
#: the rival search's grid over image space has at most this many cells, and registers its probes at most this many
#: times (cells of their boxes)
IMAGE_GRID_CELLS = 2 ** 21
IMAGE_GRID_ITEMS = 2 ** 23
#: skip the nearest probe's start where the map shows no fold near the sample (no partner, no rival candidate, and
#: the start's linear step lands within two probe spacings of the solution found): it returns there
QUIET_SKIP = True
#: a solution in a hole of the map (:class:`HoleMap`) counts as another when it reproduces the reported position to
#: the tolerance plus this (m): no data score the model there (measured on the cockpit: a truth in a hole that the
#: model reproduced only to 1.6 mm, with a tolerance of 1.1 mm)
HOLE_ALLOWANCE = 1e-3
#: a probe whose image neighbourhood spans more grid cells than this per axis is tested by every rival search
WIDE = 32


class RivalMap:
    """Probe points ``P`` (M, 3) m ``spacing`` m apart, their images ``φ(P)`` (M, 3) m and inverse Jacobians
    ``(∂φ/∂r)⁻¹`` (M, 3, 3): where to look for other solutions of ``φ(x) = v`` (:meth:`rivals`) and how to start
    inverting from them (:meth:`start_from`). Every point of a probe's cell maps within ``cell_reach`` (M,) m of
    the probe's image (one probe spacing, stretched as the map stretches it there)."""

    def __init__(self, field: GridField, points: np.ndarray, spacing: float, solver: str = "closed-form",
                 hemisphere: str = "+x"):
        def phi(at):
            return distortion(at, field.evaluate(at)[0], solver=solver, hemisphere=hemisphere)[0]

        h = 1e-5
        J = np.empty((len(points), 3, 3))
        for k in range(3):  # central differences
            step = np.zeros(3)
            step[k] = h
            J[..., k] = (phi(points + step) - phi(points - step)) / (2 * h)
        images = phi(points)
        good = np.all(np.isfinite(images), axis=1) & np.all(np.isfinite(J.reshape(-1, 9)), axis=1)
        good &= np.abs(np.linalg.det(np.where(good[:, None, None], J, np.eye(3)))) > 1e-6
        self.spacing = float(spacing)
        self.probes, self.images, self.jacobian = points[good], images[good], J[good]
        self.inverse = np.linalg.inv(self.jacobian)
        self.stretch = np.linalg.norm(self.jacobian, ord=2, axis=(1, 2))
        self.reach = 4.0 * self.spacing * max(float(np.max(self.stretch, initial=0.0)), 1.0)
        self.cell_reach = self.stretch * self.spacing * np.sqrt(3.0) / 2
        self.max_cell_reach = float(np.max(self.cell_reach, initial=0.0))
        # the rival search's probes (their region keys: blocks of REGION probe spacings) and its grid over image space
        block = np.floor(self.probes / (REGION * self.spacing)).astype(np.int64)
        region = (block[:, 0] * 1_000_003 + block[:, 1]) * 1_000_003 + block[:, 2]
        self._rival_probes = tuple(_pose_kernels.RivalProbes(self.probes, self.images, self.cell_reach, region))
        self._image_grid = tuple(self._grid_over_images(self.images, self.cell_reach)) if len(self.probes) else None

    @staticmethod
    def _grid_over_images(images: np.ndarray, reach: np.ndarray) -> _pose_kernels.ImageGrid:
        """A uniform grid over image space (:data:`~ivc.correct.reported_kernels.ImageGrid`) of cells the median
        ``reach`` (m) wide, or wider where it would have more than :data:`IMAGE_GRID_CELLS` cells or register the
        probes more than :data:`IMAGE_GRID_ITEMS` times: each probe registered in every cell that the ball of its
        reach (M,) m about its image (M, 3) m touches, or, where its box would span more than :data:`WIDE` cells per
        axis, listed as wide (every query tests it). The balls and boxes are ``pad`` wider than the reach: a probe
        the search takes (its distance computed in floating point) is never lost to the rounding of a cell's
        bounds."""
        size = float(np.median(reach))
        while True:
            pad = 1e-6 * size
            wide = 2 * (reach + 2 * pad) / size + 2 > WIDE
            low_edge, high_edge = images - (reach + 2 * pad)[:, None], images + (reach + 2 * pad)[:, None]
            origin = np.min(low_edge[~wide], axis=0)  # at least half the probes are not wide: the median's
            low = np.floor((low_edge - origin) / size).astype(np.int64)
            width = np.floor((high_edge - origin) / size).astype(np.int64) - low + 1
            shape = np.max(low[~wide] + width[~wide], axis=0)
            grow = max(np.prod(shape) / IMAGE_GRID_CELLS, np.sum(np.prod(width[~wide], axis=1)) / IMAGE_GRID_ITEMS)
            if grow <= 1:
                break
            size *= 1.01 * grow ** (1 / 3)
        listed = np.flatnonzero(~wide)
        counts = np.prod(width[listed], axis=1)
        owner = np.repeat(listed, counts)
        k = np.arange(len(owner)) - np.repeat(np.cumsum(counts) - counts, counts)
        ny, nz = width[owner, 1], width[owner, 2]
        index = low[owner] + np.stack([k // (ny * nz), (k // nz) % ny, k % nz], axis=1)
        # the cells of each box that its ball touches
        corner = origin + size * index
        gap = images[owner] - np.clip(images[owner], corner, corner + size)
        touches = np.linalg.norm(gap, axis=1) <= reach[owner] + 2 * pad
        owner, index = owner[touches], index[touches]
        cell = (index[:, 0] * shape[1] + index[:, 1]) * shape[2] + index[:, 2]
        start = np.concatenate([[0], np.cumsum(np.bincount(cell, minlength=int(np.prod(shape))))])
        items = owner[np.argsort(cell, kind="stable")]
        return _pose_kernels.ImageGrid(origin, size, shape, start, items, np.flatnonzero(wide), pad)

    def rivals(self, v: np.ndarray, r: np.ndarray, tolerance: np.ndarray, limit: int = RIVALS, serial: bool = False
               ) -> tuple[np.ndarray, np.ndarray]:
        """Probes from which to look for another solution of ``φ(x) = v``: for reported positions v (n, 3) m solved at
        r (n, 3) m, the probes farther than two probe spacings from r whose cell can map within ``tolerance`` (n,) m
        of v (``|φ(p) − v| − cell_reach ≤ tolerance``), one per region (blocks of three probe spacings; the nearest in
        image), at most ``limit`` regions per sample, nearest in image first (ties: the smaller region key).
        Returns (sample rows, probe indices), by row. Compiled
        (:func:`ivc.correct.reported_kernels.rivals_kernel`, ``serial``: without threads), on a grid over the
        probes' images built once."""
        v, r = np.ascontiguousarray(v, dtype=float), np.ascontiguousarray(r, dtype=float)
        tolerance = np.ascontiguousarray(tolerance, dtype=float)
        n = len(v)
        if v.shape != (n, 3) or r.shape != (n, 3) or tolerance.shape != (n,) or limit < 0:
            raise InputError(f"the rival search needs positions (n, 3), solutions (n, 3) and tolerances (n,) and a "
                             f"limit >= 0, got {v.shape}, {r.shape}, {tolerance.shape} and {limit}")
        if self._image_grid is None:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        probe, count = np.empty((n, int(limit)), dtype=np.int64), np.empty(n, dtype=np.int64)
        kernel = compiled.choose(_pose_kernels.rivals_serial if serial else _pose_kernels.rivals_kernel, n)
        kernel(v, r, tolerance, self._rival_probes, self._image_grid, 2 * self.spacing,
               tuple(_pose_kernels.RivalOutput(probe, count)))
        return np.repeat(np.arange(n), count), probe[np.arange(int(limit)) < count[:, None]]

    def start_from(self, probes: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The linear start ``p + (∂φ/∂r)⁻¹ (v − φ(p))`` (n, 3) and its inverse Jacobian (n, 3, 3) from probes."""
        H = self.inverse[probes]
        return (np.ascontiguousarray(self.probes[probes] + np.einsum("nij,nj->ni", H, v - self.images[probes])),
                np.ascontiguousarray(H))

class SeedMap(RivalMap):
    """Where to start inverting ``φ``: a :class:`RivalMap` over the mapped volume (probes on the table's grid refined
    ``subdivision`` times) and, for each probe, the index of a distant probe whose image lies near its own (−1:
    none), see the module docstring."""

    def __init__(self, field: GridField, solver: str = "closed-form", hemisphere: str = "+x",
                 subdivision: int = SUBDIVISION):
        grid = field.grid
        spacing = grid.spacing / subdivision
        axes = [grid.origin[a] + spacing * np.arange((grid.shape[a] - 1) * subdivision + 1) for a in range(3)]
        fine = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        probes = fine[field.evaluate(fine)[2]]
        if len(probes) == 0:
            raise InputError("the table has no mapped cell to correct in")
        super().__init__(field, probes, spacing, solver, hemisphere)
        self.tree = cKDTree(self.images)
        #: where the map turns space inside out at each probe (det ∂φ/∂r < 0)
        self.reversed = np.linalg.det(self.jacobian) < 0
        # a probe's image neighbourhood: one probe spacing, stretched as the map stretches it there
        radius = self.stretch * self.spacing
        self.partner = np.full(len(self.probes), -1)
        near = self.tree.query_ball_point(self.images, radius)
        counts = np.fromiter((len(n) for n in near), dtype=np.int64, count=len(near))
        i = np.repeat(np.arange(len(near)), counts)
        j = np.fromiter((k for n in near for k in n), dtype=np.int64, count=int(counts.sum()))
        apart = self.probes[j] - self.probes[i]
        linear = np.einsum("nij,nj->ni", self.inverse[i], self.images[j] - self.images[i])
        distance = np.linalg.norm(apart, axis=1)
        # another branch: far apart, and not where the local linear map puts it
        far = (distance > 2 * self.spacing) & (np.linalg.norm(apart - linear, axis=1) > 0.5 * distance)
        i, j = i[far], j[far]
        if len(i):
            order = np.lexsort((np.linalg.norm(self.images[j] - self.images[i], axis=1), i))
            i, j = i[order], j[order]
            first = np.r_[True, i[1:] != i[:-1]]  # per probe, its partner with the nearest image
            self.partner[i[first]] = j[first]

    @property
    def ambiguous_fraction(self) -> float:
        """Share of the probes whose images overlap those of a distant region."""
        return float(np.mean(self.partner >= 0))

    def starts(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For reported positions v (n, 3): start (n, 3) and H (n, 3, 3) from the nearest probe image, and the
        partner's start and H (NaN and I where there is none). Far from every image: v and I."""
        n = len(v)
        eye = np.broadcast_to(np.eye(3), (n, 3, 3))
        # a batch's query on as many threads as numba's kernels (the same answer: each point's query is its own)
        workers = numba.get_num_threads() if n >= 1024 else 1
        distance, index = self.tree.query(np.where(np.isfinite(v), v, 0.0), workers=workers)
        near = np.isfinite(distance) & (distance <= self.reach) & np.all(np.isfinite(v), axis=1)
        index = np.where(near, index, 0)

        def from_probe(i):
            H = self.inverse[i]
            return self.probes[i] + np.einsum("nij,nj->ni", H, v - self.images[i]), H

        start, H = from_probe(index)
        start = np.where(near[:, None], start, v)
        H = np.where(near[:, None, None], H, eye)
        partner = np.where(near, self.partner[index], -1)
        has = partner >= 0
        p_start, p_H = from_probe(np.where(has, partner, 0))
        p_start = np.where(has[:, None], p_start, np.nan)
        p_H = np.where(has[:, None, None], p_H, eye)
        return np.ascontiguousarray(start), np.ascontiguousarray(H), np.ascontiguousarray(p_start), \
            np.ascontiguousarray(p_H)


def hole_nodes(table: LookupTable) -> np.ndarray:
    """The table's holes, (nx, ny, nz) bool: the grid's unmapped nodes where the table holds the values of a field
    model that holds between its data. That is an equivalent-source model (sources outside the working volume, a
    physical field throughout the grid, which spans the samples). A polynomial's values off its data are an
    extrapolation that grows without bound (measured on the default scene's cube map: the map's stretch up to 80
    on the grid's margin, where every sample then had two or three false starts): no holes there."""
    shape = table.grid.shape
    if not str(table.fit.get("method", "")).startswith("equivalent sources"):
        return np.zeros(shape, dtype=bool)
    filled = np.all(np.isfinite(np.asarray(table.values).reshape(*shape, -1)), axis=-1)
    return filled & ~np.asarray(table.valid, bool)


class HoleMap(RivalMap):
    """Rivals the mapped volume cannot show: a :class:`RivalMap` at the table's holes (:func:`hole_nodes`), with
    ``field`` the table over its mapped nodes and its holes. A pose whose reported position a hole can also produce
    is as ambiguous as one that two mapped regions produce: the model there is less certain (a solution there counts
    to :data:`HOLE_ALLOWANCE` more), but where it puts a solution the truth may be (measured on the cockpit's
    whole-volume map from reported poses: 106 of the 107 trusted poses more than 2 mm off had their truth in a hole,
    up to 85 mm from the mapped volume; docs/trust.md)."""

    def __init__(self, table: LookupTable, holes: np.ndarray, interpolation: str = "cubic",
                 solver: str = "closed-form", hemisphere: str = "+x"):
        grid = table.grid
        self.field = GridField(grid, table.values, np.asarray(table.valid, bool) | holes, interpolation)
        super().__init__(self.field, grid.nodes()[holes], grid.spacing, solver, hemisphere)

    @classmethod
    def of(cls, table: LookupTable, interpolation: str = "cubic", hemisphere: str = "+x") -> HoleMap | None:
        """The table's hole map, or None where it has no holes (nothing to search)."""
        holes = hole_nodes(table)
        return cls(table, holes, interpolation, "closed-form", hemisphere) if holes.any() else None


def table_solver(table: LookupTable) -> str:
    """The tracker solver a table was fitted for (``closed-form`` for tables fitted from signals)."""
    return str(table.fit.get("tracker_solver", "closed-form"))


class PoseCorrector:
    """Applies a table to reported poses: :meth:`batch` for arrays of frames, :meth:`update` for a stream.

    ``solver``: the tracker's pose solver (default: the one the table was fitted for, else
    ``closed-form``). ``hemisphere``: default the table's. ``max_residual``: the HIGH_RESIDUAL
    threshold in metres. ``check_ambiguity``: also invert each sample (not a stream's continuing
    track) from its nearest probe and that probe's partner, and flag distinct mapped solutions.
    ``precision``, ``max_precision`` (m), ``signal_noise``: the predicted precision and its gate, as
    :class:`~ivc.correct.Corrector`'s (the noise: what the table's fit measured on the reported poses of the
    static steps, or on their signals). ``table_error``: add the map's own error that the table's fit measured
    (:attr:`~ivc.table.lookup.LookupTable.map_error`) to the predicted precision, in quadrature.
    """

    def __init__(self, table: LookupTable | GridField, hemisphere: str | None = None, interpolation: str = "cubic",
                 solver: str | None = None, max_residual: float = MAX_RESIDUAL_M,
                 max_iterations: int = MAX_ITERATIONS, tolerance: float = TOLERANCE, check_ambiguity: bool = True,
                 precision: bool = True, max_precision: float | str | None = DEFAULT,
                 signal_noise: float | None = None, table_error: bool = True):
        self.field = table.field(interpolation) if isinstance(table, LookupTable) else table
        error = table.map_error if table_error and isinstance(table, LookupTable) else None
        #: the map's own RMS error (position m, orientation rad) added to the predicted precision
        self.map_error = (0.0, 0.0) if error is None else error
        if solver is None:
            solver = table_solver(table) if isinstance(table, LookupTable) else "closed-form"
        self.solver = check_solver(solver)
        self.hemisphere = hemisphere or (table.hemisphere if isinstance(table, LookupTable) else "+x")
        self._h = hemisphere_vector(self.hemisphere)
        if not max_residual > 0:
            raise InputError(f"max_residual must be positive (metres), got {max_residual}")
        self.max_residual = float(max_residual)
        self.max_iterations = int(max_iterations)
        self.tolerance = float(tolerance)
        # per sensor (row ``_slot[key]``): the previous good correction offset r − v, and whether it is current
        self._slot: dict = {}
        self._slot_cache: dict = {}
        self._offset = np.zeros((16, 3))
        self._tracked = np.zeros(16, dtype=bool)
        self._seeds: SeedMap | None = None
        self._table = table if isinstance(table, LookupTable) else None
        self._interpolation = interpolation
        self._holes: HoleMap | None | bool = False  # False: not built yet
        self.check_ambiguity = bool(check_ambiguity)
        self.gate = PrecisionGate.resolve(table, precision, max_precision, signal_noise)
        #: which samples of the last batch (or frame) were flagged as ambiguous (their map has two branches there)
        self.last_ambiguous = np.zeros(0, dtype=bool)

    @property
    def seeds(self) -> SeedMap:
        """The probe map the inversions start from (built on first use)."""
        if self._seeds is None:
            # starts only: the closed form's map is close to any equivariant solver's and far cheaper
            self._seeds = SeedMap(self.field, "closed-form", self.hemisphere)
        return self._seeds

    @property
    def holes(self) -> HoleMap | None:
        """The rival map of the grid's unmapped nodes where the table holds values (built on first use; None: none)."""
        if self._holes is False:
            self._holes = None if self._table is None else HoleMap.of(self._table, self._interpolation,
                                                                       self.hemisphere)
        return self._holes

    def _invert(self, v, start, H, serial, restarts: int = 0, field: GridField | None = None,
                known: np.ndarray | None = None):
        """Invert ``φ`` at reported positions v (n, 3) m from ``start`` (n, 3) m with inverse-Jacobian estimates H
        (n, 3, 3), in ``field`` (default the table's mapped field). ``known`` (n, 3) m: the solution each search
        has already; a search that comes back to it stops there (the compiled solver only)."""
        n = len(v)
        f = self.field if field is None else field
        if self.solver == "closed-form":
            r, C = np.empty((n, 3)), np.empty((n, 3, 3))
            miss, converged = np.empty(n), np.empty(n, dtype=bool)
            iterations, mapped = np.empty(n, dtype=np.int64), np.empty(n, dtype=bool)
            kernel = compiled.choose(_pose_kernels.invert_serial if serial else _pose_kernels.invert_kernel, n)
            limits = _pose_kernels.Limits(int(self.max_iterations), float(self.tolerance), int(restarts))
            out = _pose_kernels.InvertOutput(miss, converged, iterations, mapped)
            known = np.full((n, 3), np.nan) if known is None else np.ascontiguousarray(known, dtype=float)
            kernel(v, start, H.copy(), known, self._h, f.kernel_grid, tuple(limits), r, C, tuple(out))
            return r, C, miss, converged, iterations, mapped
        inv = invert_distortion(v, lambda r: f.evaluate(r)[0], self.solver, self.hemisphere, start, self.tolerance,
                                self.max_iterations)
        ok = np.all(np.isfinite(inv.position), axis=1)
        mapped = f.evaluate(np.where(ok[:, None], inv.position, 0.0))[2] & ok
        return inv.position, inv.turn, inv.miss, inv.converged, inv.iterations, mapped

    def _run(self, v: np.ndarray, Q: np.ndarray, previous: np.ndarray, serial: bool, restarts: int = 0
             ) -> Correction:
        """Correct reported positions v (n, 3) and rotations Q (n, 3, 3); ``previous`` (n, 3): each sample's
        previous good correction offset r − v (NaN: none), which then starts the inversion; ``restarts``: the
        inversion's recomputations of its inverse Jacobian where Broyden's estimate stalls."""
        n = len(v)
        finite = np.all(np.isfinite(v), axis=1) & np.all(np.isfinite(Q.reshape(n, 9)), axis=1)
        v = np.ascontiguousarray(np.where(finite[:, None], v, 1.0))
        tracked = np.all(np.isfinite(previous), axis=1)
        start = np.where(tracked[:, None], v + np.where(tracked[:, None], previous, 0.0), v)
        eye = np.broadcast_to(np.eye(3), (n, 3, 3))
        r, C, miss, converged, iterations, mapped = self._invert(v, start, eye, serial, restarts)
        self._restart(v, r, C, miss, converged, iterations, mapped, finite & ~tracked, serial, restarts)
        ambiguous = np.zeros(n, dtype=bool)
        # a stream's continuing track needs no other start: its history tells which branch; nor does a sample whose
        # inversion failed from its reported position and, away from folds, from the nearest probe (_restart): it is
        # flagged already, and the rival starts' solutions are not taken (measured: most often the wrong branch)
        check = np.flatnonzero(finite & ~tracked & converged & mapped) if self.check_ambiguity else np.zeros(0, int)
        if len(check):
            ambiguous[check], extra = self._ambiguous(v[check], Q[check], r[check], serial)
            iterations[check] += extra
        q, flags = np.empty((n, 4)), np.empty(n, dtype=np.uint8)
        contiguous = np.ascontiguousarray
        compose = compiled.choose(_pose_kernels.compose_kernel, n)
        compose(contiguous(C, dtype=float), contiguous(Q, dtype=float),
                contiguous(mapped, dtype=bool), contiguous(converged, dtype=bool),
                contiguous(miss, dtype=float), self.max_residual, q, flags)
        flags[ambiguous] |= HIGH_RESIDUAL
        self.last_ambiguous = ambiguous
        flags[~finite] = INVALID_INPUT
        r[~finite], q[~finite], miss[~finite], iterations[~finite] = np.nan, np.nan, np.nan, 0
        if not self.gate.predicts:
            return Correction(r, q, flags, miss, iterations)
        precision, orientation_precision = self.predict_precision(v, Q, r, serial)
        self.gate.apply(precision, flags, finite)
        return Correction(r, q, flags, miss, iterations, precision, orientation_precision)

    def _restart(self, v, r, C, miss, converged, iterations, mapped, untracked, serial, restarts) -> None:
        """Invert again, from the probe nearest in image (:meth:`SeedMap.starts`), the untracked samples whose
        inversion from their reported position failed, where the map does not fold near them (in place). Next to
        strong metal a reported position lies hundreds of millimetres from its true one, often outside the mapped
        volume, where an inversion started there cannot go. Only where none of the :data:`NEAR_PROBES` probes
        nearest in image has a partner (a distant probe with an image near its own) or lies where the map turns
        space inside out: near a fold the restart can land on one sheet while the truth lies on another that the
        rival search does not reach (measured on the strong scene: restarted everywhere, 7-8 of 1,955 check poses
        trusted 1-130 mm off)."""
        failed = np.flatnonzero(untracked & ~(converged & mapped & (miss <= self.max_residual)))
        if not len(failed):
            return
        seeds = self.seeds
        p_start, p_H, _, _ = seeds.starts(v[failed])
        _, near = seeds.tree.query(v[failed], k=min(NEAR_PROBES, len(seeds.probes)))
        near = near.reshape(len(failed), -1)
        folds = np.any((seeds.partner[near] >= 0) | seeds.reversed[near], axis=1)
        ok = np.all(np.isfinite(p_start), axis=1) & ~folds
        failed, p_start, p_H = failed[ok], p_start[ok], p_H[ok]
        if not len(failed):
            return
        r2, C2, miss2, conv2, it2, mapped2 = self._invert(np.ascontiguousarray(v[failed]), p_start, p_H, serial,
                                                          restarts)
        iterations[failed] += it2
        took = conv2 & mapped2 & (miss2 <= self.max_residual)
        rows = failed[took]
        r[rows], C[rows], miss[rows], converged[rows], mapped[rows] = r2[took], C2[took], miss2[took], True, True

    def predict_precision(self, v: np.ndarray, Q: np.ndarray, r: np.ndarray, serial: bool = False
                          ) -> tuple[np.ndarray, np.ndarray]:
        """Predicted RMS position (n,) m and orientation (n,) rad errors of the poses corrected from reported
        positions v (n, 3) m and rotations Q (n, 3, 3) to positions r (n, 3) m: the tracker's noise carried
        through the map (:func:`ivc.pose.precision.reported_pose_covariance`, compiled for the closed-form
        solver) and the map's own error (:attr:`map_error`), in quadrature. NaN where any of them is not
        finite."""
        n = len(v)
        usable = np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(v), axis=1) & np.all(
            np.isfinite(Q.reshape(n, 9)), axis=1)
        r_in = np.ascontiguousarray(np.where(usable[:, None], r, np.nan))
        if self.solver == "closed-form":
            out_r, out_a = np.empty(n), np.empty(n)
            kernel = compiled.choose(_pose_kernels.precision_serial if serial else _pose_kernels.precision_kernel, n)
            kernel(r_in, self._h, self.field.kernel_grid, float(self.gate.sigma), out_r, out_a)
            return self._with_map_error(out_r, out_a)
        at = np.where(usable[:, None], r, 1.0)
        g, dg, _ = self.field.evaluate(at)
        _, _, d_phi, d_omega, d_field = distortion(at, g.reshape(n, 3, 3), dg.reshape(n, 3, 3, 3), self.solver,
                                                   self.hemisphere, jacobian=True)
        Q = np.where(usable[:, None, None], Q, np.eye(3))
        out_r, out_a = traces(reported_pose_covariance(Q, d_phi, d_omega, d_field, float(self.gate.sigma)))
        out_r[~usable], out_a[~usable] = np.nan, np.nan
        return self._with_map_error(out_r, out_a)

    def _with_map_error(self, position: np.ndarray, orientation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The predicted precision (m, rad) with the map's own error added in quadrature (in place)."""
        if self.map_error != (0.0, 0.0):
            np.hypot(position, self.map_error[0], out=position)
            np.hypot(orientation, self.map_error[1], out=orientation)
        return position, orientation

    def _ambiguous(self, v, Q, r, serial) -> tuple[np.ndarray, np.ndarray]:
        """Whether each reported position v (n, 3) m, solved at r (n, 3) m, has another mapped
        solution, and the iterations spent looking. Another solution is one more than :data:`AMBIGUITY` from r
        that reproduces v to a tolerance: :data:`RIVAL_NOISE` times the reported position's predicted RMS noise
        where the noise is known (a region that produces v within the noise is as likely the truth), else
        ``max_residual``. It is looked for from the nearest probe (:meth:`SeedMap.starts`: its start and its
        partner's) and from :data:`RIVALS` probes elsewhere whose cells can map within the tolerance
        (:meth:`SeedMap.rivals`). A search that comes back to within
        :data:`~ivc.correct.reported_kernels.RETURNED` of r stops there."""
        n = len(v)
        tolerance = np.full(n, self.max_residual)
        if self.gate.predicts:
            noise = reported_noise(v, Q, float(self.gate.sigma))
            tolerance = np.maximum(tolerance, np.where(np.isfinite(noise), RIVAL_NOISE * noise, np.inf))
        p_start, p_H, q_start, q_H = self.seeds.starts(v)
        has = np.all(np.isfinite(q_start), axis=1)
        rows, probes = self.seeds.rivals(v, r, np.minimum(tolerance, self.seeds.reach), serial=serial)
        r_start, r_H = self.seeds.start_from(probes, v[rows])
        holes = self.holes
        loose = tolerance + HOLE_ALLOWANCE
        h_rows, h_probes = (holes.rivals(v, r, np.minimum(loose, holes.reach), serial=serial) if holes is not None
                            else (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)))
        # the nearest probe's start is needed where the map may fold: a partner, a rival candidate, or a start that the
        # linear step puts away from the solution found. Elsewhere it returns to r (measured on the default, severe and
        # cockpit scenes' check poses: never another solution there), and skipping it saves a fifth of the work
        folds = has | (np.bincount(rows, minlength=n) > 0) | (np.bincount(h_rows, minlength=n) > 0)
        near = folds | ~(np.linalg.norm(p_start - r, axis=1) <= 2 * self.seeds.spacing) | (not QUIET_SKIP)
        idx = np.concatenate([np.flatnonzero(near), np.flatnonzero(has), rows])
        start = np.concatenate([p_start[near], q_start[has], r_start])
        H = np.concatenate([p_H[near], q_H[has], r_H])
        # numba's threads take equal contiguous shares: interleave the cheap nearest-probe starts with the partner and
        # rival ones (about twice the iterations each). Every inversion is its own, so the order changes no result
        threads = numba.get_num_threads()
        order = np.concatenate([np.arange(t, len(idx), threads) for t in range(threads)])
        idx, start, H = idx[order], start[order], H[order]
        r2, _, miss2, _, it2, mapped2 = self._invert(np.ascontiguousarray(v[idx]), np.ascontiguousarray(start),
                                                     np.ascontiguousarray(H), serial, _pose_kernels.RESTARTS,
                                                     known=r[idx])
        other = mapped2 & (miss2 <= tolerance[idx]) & (np.linalg.norm(r2 - r[idx], axis=1) > AMBIGUITY)
        ambiguous = np.zeros(n, dtype=bool)
        ambiguous[idx[other]] = True
        iterations = np.bincount(idx, weights=it2, minlength=n)
        # and from the holes of the map, in the model the table holds there: each sample's hole probes in turn, nearest
        # in image first, until one finds another solution (a sample that is ambiguous already needs no more; most
        # hole searches find none and cost about ten iterations each: a sixth fewer of them on the cockpit)
        rank = np.arange(len(h_rows)) - np.searchsorted(h_rows, h_rows)  # h_rows comes by row
        for k in range(int(rank.max(initial=-1)) + 1):
            turn = (rank == k) & ~ambiguous[h_rows]
            rows, probes = h_rows[turn], h_probes[turn]
            if not len(rows):
                break
            h_start, h_H = holes.start_from(probes, v[rows])
            r3, _, miss3, _, it3, inside3 = self._invert(np.ascontiguousarray(v[rows]), h_start, h_H, serial,
                                                         _pose_kernels.RESTARTS, holes.field, known=r[rows])
            other = inside3 & (miss3 <= loose[rows]) & (np.linalg.norm(r3 - r[rows], axis=1) > AMBIGUITY)
            ambiguous[rows[other]] = True
            iterations += np.bincount(rows, weights=it3, minlength=n)
        return ambiguous, iterations.astype(np.int64)

    def invert_from_probes(self, position: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Invert ``φ`` at reported positions (n, 3) m from each one's nearest probe of :attr:`seeds` rather than
        from the position itself: (true positions (n, 3) m, whether each reproduces its reported position to
        ``max_residual``, whether it is in the mapped volume). No ambiguity test: a start of last resort, for
        grids an export fills (ivc.export.distortion), never for trusting a measurement."""
        v = np.ascontiguousarray(np.asarray(position, float).reshape(-1, 3))
        start, H, _, _ = self.seeds.starts(v)
        r, _, miss, converged, _, mapped = self._invert(v, start, H, serial=False)
        return r, converged & (miss <= self.max_residual), mapped

    def batch(self, position: np.ndarray, quaternion: np.ndarray, valid: np.ndarray | None = None) -> Correction:
        """Correct reported poses: positions (..., 3) m and quaternions (..., 4) [w, x, y, z], each sample on
        its own. Samples with ``valid`` False are flagged INVALID_INPUT. ``residual`` is |v − φ(r)| in m."""
        position, quaternion = np.asarray(position, float), np.asarray(quaternion, float)
        if position.shape[-1:] != (3,) or quaternion.shape != position.shape[:-1] + (4,):
            raise InputError(f"reported poses need positions (..., 3) and quaternions (..., 4) of the same leading "
                             f"shape, got {position.shape} and {quaternion.shape}")
        lead = position.shape[:-1]
        v = position.reshape(-1, 3)
        with np.errstate(invalid="ignore"):
            Q = rotations.to_matrix(quaternion.reshape(-1, 4))
        if valid is not None:
            bad = ~np.asarray(valid, bool).reshape(-1)
            v = np.where(bad[:, None], np.nan, v)
        out = self._run(v, Q, np.full((len(v), 3), np.nan), serial=len(v) < 64)
        shaped = (None if a is None else a.reshape(lead) for a in (out.precision, out.orientation_precision))
        return Correction(out.position.reshape(*lead, 3), out.quaternion.reshape(*lead, 4), out.flags.reshape(lead),
                          out.residual.reshape(lead), out.iterations.reshape(lead), *shaped)

    def track(self, position: np.ndarray, quaternion: np.ndarray, valid: np.ndarray | None = None) -> Correction:
        """Correct a recorded time series of reported poses, positions (F, N, 3) m and quaternions (F, N, 4), frame
        by frame per sensor as a stream would be (:meth:`update`'s branch logic): every sample as :meth:`batch`
        does, then each sample flagged only as ambiguous whose sensor's previous frame is trusted is corrected again
        from that frame's correction offset; kept when its offset moved at most :data:`TRACK_JUMP`. A track that
        starts in an ambiguous region stays flagged until it leaves it. No sensor's warm start is touched."""
        position, quaternion = np.asarray(position, float), np.asarray(quaternion, float)
        if position.ndim != 3 or position.shape[-1] != 3 or quaternion.shape != position.shape[:-1] + (4,):
            raise InputError(f"a track needs positions (F, N, 3) and quaternions (F, N, 4), got {position.shape} "
                             f"and {quaternion.shape}")
        out = self.batch(position, quaternion, valid)
        if not self.check_ambiguity:
            return out
        ambiguous = self.last_ambiguous.reshape(position.shape[:2]) & (out.flags == HIGH_RESIDUAL)
        frames = np.flatnonzero(ambiguous[1:].any(axis=1)) + 1
        for f in frames:  # in time order: a sample resolved here continues the track for the next frame
            k = np.flatnonzero(ambiguous[f] & (out.flags[f - 1] == 0))
            if not len(k):
                continue
            v = position[f, k]
            previous = out.position[f - 1, k] - position[f - 1, k]
            with np.errstate(invalid="ignore"):
                Q = rotations.to_matrix(quaternion[f, k])
            again = self._run(v, Q, previous, serial=True)
            keep = (again.flags == 0) & (np.linalg.norm(again.position - v - previous, axis=1) <= TRACK_JUMP)
            out.assign((f, k[keep]), again, keep)
        return out

    def update(self, position: np.ndarray, rotation: np.ndarray, sensors: list | tuple | None = None) -> Correction:
        """Correct the latest frame of a stream: positions (N, 3) m and rotation matrices (N, 3, 3), one per
        sensor. Each sensor starts from its reported position moved by its own previous good correction
        (keyed by ``sensors``, default 0..N−1), or from the reported position.

        For the closed-form solver, a frame whose sensors all continue a track (or any frame without the
        ambiguity test) is corrected by one compiled call (:func:`ivc.correct.reported_kernels.stream_kernel`),
        the same steps as :meth:`batch` from another start; other frames go through the batch's path.
        """
        v = np.ascontiguousarray(np.asarray(position, dtype=float).reshape(-1, 3))
        Q = np.ascontiguousarray(np.asarray(rotation, dtype=float).reshape(-1, 3, 3))
        if len(Q) != len(v):
            raise InputError(f"a frame needs one rotation per position, got {len(v)} positions and {len(Q)} rotations")
        slots = self._slots(sensors, len(v))
        if self.check_ambiguity:
            before = np.where(self._tracked[slots][:, None], self._offset[slots], np.nan)
            out = self._update(v, Q, slots)
            # a continuing track whose correction jumps is not continuing: that sample gets the full test
            jumped = np.linalg.norm(out.position - v - before, axis=1) > TRACK_JUMP
            if jumped.any():
                again = self._run(v[jumped], Q[jumped], np.full((int(jumped.sum()), 3), np.nan), serial=True)
                out.assign(jumped, again)
                for n in np.flatnonzero(jumped):
                    slot = slots[n]
                    self._tracked[slot] = out.flags[n] == 0
                    if out.flags[n] == 0:
                        self._offset[slot] = out.position[n] - v[n]
            return out
        return self._update(v, Q, slots)

    def _update(self, v: np.ndarray, Q: np.ndarray, slots: np.ndarray) -> Correction:
        """:meth:`update` of a frame whose sensors are ``slots``."""
        if self.solver == "closed-form" and (not self.check_ambiguity or self._tracked[slots].all()):
            n = len(v)
            r, q, flags = np.empty((n, 3)), np.empty((n, 4)), np.empty(n, dtype=np.uint8)
            miss, iterations = np.empty(n), np.empty(n, dtype=np.int64)
            f = self.field
            stream = compiled.choose(_pose_kernels.stream_kernel, n)
            stream(v, Q, (slots, self._offset, self._tracked), self._h, f.kernel_grid, self._stream_limits(),
                   self.max_residual, (r, q, flags, miss, iterations))  # Tracks, StreamOutput (reported_kernels)
            if not self.gate.predicts:
                return Correction(r, q, flags, miss, iterations)
            precision, orientation_precision = self.predict_precision(v, Q, r, serial=True)
            self.gate.apply(precision, flags, (flags & INVALID_INPUT) == 0)
            self._tracked[slots[flags != 0]] = False  # a pose the gate flags continues no track
            return Correction(r, q, flags, miss, iterations, precision, orientation_precision)
        tracked = self._tracked[slots]
        offsets = np.where(tracked[:, None], self._offset[slots], np.nan)
        out = self._run(v, Q, offsets, serial=True)
        for n, slot in enumerate(slots):  # in order, as the compiled path: a sensor named twice keeps its last
            self._tracked[slot] = out.flags[n] == 0
            if out.flags[n] == 0:
                self._offset[slot] = out.position[n] - v[n]
        return out

    def warm_starts(self, sensors: list | tuple | str) -> np.ndarray:
        """Each named sensor's current warm start for :meth:`update`: its previous good correction offset
        ``r − v`` (n, 3) m, NaN where it has none (a new sensor, after a flagged sample or :meth:`reset`)."""
        slots = self._slots(sensors, len(tuple(sensors)))
        return np.where(self._tracked[slots][:, None], self._offset[slots], np.nan)

    def correct_from(self, position: np.ndarray, rotation: np.ndarray, offsets: np.ndarray, restarts: int = 0
                     ) -> Correction:
        """The batch's path for reported positions (n, 3) m and rotations (n, 3, 3), each sample started at
        ``position + offsets`` ((n, 3) m; a NaN row: at the position, with the ambiguity test), without touching
        any sensor's warm start: what :meth:`update` computes for a frame, in the batch's steps. ``restarts``: how
        often the inversion may recompute its inverse Jacobian where Broyden's estimate stalls (near a fold; the
        correction's own inversion makes none, the ambiguity test's searches
        :data:`~ivc.correct.reported_kernels.RESTARTS`)."""
        v = np.ascontiguousarray(np.asarray(position, dtype=float).reshape(-1, 3))
        Q = np.asarray(rotation, dtype=float).reshape(-1, 3, 3)
        offsets = np.asarray(offsets, dtype=float).reshape(-1, 3)
        if not len(v) == len(Q) == len(offsets):
            raise InputError(f"{len(v)} positions, {len(Q)} rotations and {len(offsets)} offsets: give one each")
        return self._run(v, Q, offsets, serial=True, restarts=restarts)

    def warm_up(self, position: np.ndarray) -> None:
        """Run the compiled steps of :meth:`batch` and :meth:`update` once, at a reported position (3,) m, so
        that a stream's first frames do not wait for them; no sensor's warm start is touched."""
        v = np.asarray(position, dtype=float).reshape(1, 3)
        Q = np.eye(3)[None]
        self.correct_from(v, Q, np.zeros((1, 3)))
        if self.check_ambiguity:  # a track's first frame: the probe maps built, the ambiguity test compiled
            self.correct_from(v, Q, np.full((1, 3), np.nan))
        if self.solver == "closed-form":
            out = [np.empty((1, 3)), np.empty((1, 4)), np.empty(1, dtype=np.uint8), np.empty(1),
                   np.empty(1, dtype=np.int64)]
            tracks = (np.zeros(1, dtype=np.int64), np.zeros((1, 3)), np.ones(1, dtype=bool))
            _pose_kernels.stream_kernel(np.ascontiguousarray(v), Q, tracks, self._h, self.field.kernel_grid,
                                        self._stream_limits(), self.max_residual, tuple(out))

    def _stream_limits(self) -> tuple:
        """The stream kernel's :data:`~ivc.correct.reported_kernels.Limits` (no Jacobian restarts)."""
        return tuple(_pose_kernels.Limits(int(self.max_iterations), float(self.tolerance), 0))

    def _slots(self, sensors, n: int) -> np.ndarray:
        """Rows of the warm-start arrays (``_offset``, ``_tracked``) of the frame's sensors, added on first use."""
        keys = tuple(range(n)) if sensors is None else tuple(sensors)
        slots = self._slot_cache.get(keys)
        if slots is not None:
            return slots
        if len(keys) != n:
            raise InputError(f"{len(keys)} sensor names for a frame of {n} samples")
        for key in keys:
            if key not in self._slot:
                self._slot[key] = len(self._slot)
        if len(self._slot) > len(self._tracked):
            grow = max(len(self._slot), 2 * len(self._tracked))
            self._offset = np.vstack([self._offset, np.zeros((grow - len(self._offset), 3))])
            self._tracked = np.concatenate([self._tracked, np.zeros(grow - len(self._tracked), dtype=bool)])
        slots = np.array([self._slot[k] for k in keys], dtype=np.int64)
        if len(self._slot_cache) < 1024:
            self._slot_cache[keys] = slots
        return slots

    def reset(self, sensors: list | tuple | None = None) -> None:
        """Forget every sensor's warm start (after a gap in the stream), or the named ``sensors``' (a pose found
        wrong after its correction: its track does not continue)."""
        if sensors is None:
            self._tracked[:] = False
        else:
            self._tracked[[self._slot[k] for k in sensors if k in self._slot]] = False
