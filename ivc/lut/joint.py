"""Map a whole working volume from one cube placement: extension sweeps solved jointly with the map.

The cube sweep maps a ball around the cube as large as the wand's reach. Once a region is mapped,
any wand sensor inside it knows its pose as well as a corrected sensor does, so the wand can carry
the map outward (docs/lut.md, "Extension sweeps"):

1. the cube sweep is solved through the cube and gated as in ``ivc fit`` (its samples anchor the
   frame: they are placed by the declared cube pose and are never re-solved here);
2. a field model for the whole volume (equivalent sources, :mod:`ivc.lut.fit_sources`) is fitted to
   every sample so far and tabulated; a node is mapped when enough samples support it;
3. every frame of every extension sweep is re-solved as one rigid wand (:func:`solve_wand`) from
   the sensors that lie in the mapped region (found by correcting each sensor with the current
   table); the others, placed by the wand's calibration, give new samples ``G = T_n S_n − f_D(r_n)``;
4. repeat 2-3 until the map stops changing and growing.

Every frame of every sweep is solved against one field model in each round, so the error does not
compound ring by ring through a chain of separately fitted maps.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ivc import dipole, rotations
from ivc.correct.solver import Corrector
from ivc.errors import InputError
from ivc.fixtures.mapping import FixtureModel, Gates, map_sweep
from ivc.fixtures.wand import WandCalibration
from ivc.lut.fit_sources import (
    MAX_SAMPLES,
    SPACING,
    SourceModel,
    check_max_samples,
    default_sources,
    fit_sources,
    normal_equations,
    solve_normal_equations,
)
from ivc.lut.fit_steps import provenance
from ivc.lut.options import FitOptions
from ivc.lut.refine import skew
from ivc.lut.samples import FieldSamples, leverage
from ivc.lut.support import MIN_SUPPORT, node_support
from ivc.pose import levenberg_marquardt, signal_residual
from ivc.session import Session, SessionError, Step, extension_steps
from ivc.table.grid import DEFAULT_SPACING, Grid, GridField
from ivc.table.lookup import LookupTable

#: the joint map's inner shell of equivalent sources lies this far beyond the samples' bounding box (m)
SOURCE_STANDOFF = 0.09
#: the Tikhonov dampings the joint map's cross-validation chooses from (on the cockpit scene the fit's own
#: range, 1e-8 … 1e-5, chose its largest in every run)
DAMPINGS = (1e-7, 1e-6, 1e-5, 1e-4)
#: the joint map is tabulated this many times finer than its support grid (docs/lut.md, "Extension sweeps")
TABLE_SUBDIVISION = 2
#: the joint map's sources fit spreads its samples evenly over cubes this large (m), the support grid's cells
EVEN_CELL = DEFAULT_SPACING
#: the joint map's samples count with weight ``λ² / (ε² + ε_0²)`` with this ``ε_0`` (m), not the single-sweep fits'
#: 0.1 mm (``ivc.lut.samples.ERROR_FLOOR``): with the source near one face the samples' own estimated errors
#: run from 0.01 to 0.2 mm and 84 % of them lie below 0.1 mm, so that floor flattened the precision of most
#: of them (docs/lut.md, "Extension sweeps")
ERROR_FLOOR = 2e-5
#: frame numbers of extension sweep n's samples start at n * FRAME_OFFSET (folds never mix sweeps' blocks)
FRAME_OFFSET = 10_000_000

FieldFunction = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def _wand_residuals(S, scale, use, wand: WandCalibration, field: FieldFunction, r0, T0):
    """Residuals (F, W·9) and Jacobian (F, W·9, 6) of the rigid wand; only sensors in ``use`` count."""
    F, W = S.shape[:2]
    positions, rots = wand.propagate(r0, T0)
    g, dg = field(positions.reshape(-1, 3))
    M = dipole.field(positions) + g.reshape(F, W, 3, 3)
    dM = dipole.field_jacobian(positions) + dg.reshape(F, W, 3, 3, 3)
    e, J = signal_residual(S.reshape(-1, 3, 3), M.reshape(-1, 3, 3), dM.reshape(-1, 3, 3, 3), rots.reshape(-1, 3, 3))
    e, J = e.reshape(F, W, 9), J.reshape(F, W, 9, 6)
    lever = -T0[:, None] @ skew(wand.positions)[None]  # ∂r_n/∂ω for T_0 ← T_0 exp([ω]×)
    J_w = J[..., :3] @ lever + J[..., 3:] @ np.swapaxes(wand.rotations, -1, -2)[None]
    J = np.concatenate([J[..., :3], J_w], axis=-1)
    w = (use / scale)[..., None]
    return (e * w).reshape(F, -1), (J * w[..., None]).reshape(F, -1, 6)


@dataclass
class WandSolution:
    """Rigid wand poses: sensor 0's ``position`` (F, 3) m and ``rotation`` (F, 3, 3), ``converged`` (F,),
    ``residual`` (F,) rms over the used sensors of ``(S − Tᵀ M)/rms(S)``, standard errors ``position_sigma``
    (F,) m and ``angle_sigma`` (F,) rad from the fit's covariance, and ``used`` (F, W) sensors."""

    position: np.ndarray
    rotation: np.ndarray
    converged: np.ndarray
    residual: np.ndarray
    position_sigma: np.ndarray
    angle_sigma: np.ndarray
    used: np.ndarray


def solve_wand(S: np.ndarray, use: np.ndarray, wand: WandCalibration, field: FieldFunction, position0: np.ndarray,
               rotation0: np.ndarray, max_iterations: int = 40, step_tolerance: float = 1e-10) -> WandSolution:
    """Levenberg-Marquardt for the rigid wand in every frame from the sensors ``use`` (F, W) alone.

    ``S`` (F, W, 3, 3) signals; ``field(r) -> (g (n, 3, 3), ∂g/∂r (n, 3, 3, 3))`` the secondary field
    at any points (source frame); ``position0`` (F, 3), ``rotation0`` (F, 3, 3): sensor 0's starting pose.
    Each used sensor's residual is relative to its rms(S). A frame needs at least one used sensor (a
    sensor's 9 signals fix all 6 degrees of freedom); frames without one come back NaN, not converged.
    """
    S, use, scale, r, T, active = _prepare(S, use, wand, position0, rotation0)
    e, J = _wand_residuals(S, scale, use, wand, field, r, T)

    def trial(idx, step):
        trial_r = r[idx] + step[:, :3]
        trial_T = T[idx] @ rotations.to_matrix(rotations.from_rotvec(step[:, 3:]))
        return (trial_r, trial_T), *_wand_residuals(S[idx], scale[idx], use[idx], wand, field, trial_r, trial_T)

    converged, _ = levenberg_marquardt((r, T), e, J, active, trial, max_iterations, step_tolerance)
    return _wand_solution(r, T, converged, active, use, np.sum(e**2, axis=1), np.swapaxes(J, -1, -2) @ J)


def _prepare(S, use, wand, position0, rotation0):
    """Checked signals, used sensors, their rms(S), starting poses and the active frames of a wand solve."""
    S = np.asarray(S, float)
    use = np.asarray(use, bool)
    if S.ndim != 4 or S.shape[2:] != (3, 3) or use.shape != S.shape[:2]:
        raise InputError(f"solve_wand: S must be (F, W, 3, 3) and use (F, W), got {S.shape} and {use.shape}")
    if S.shape[1] != len(wand.positions):
        raise InputError(f"solve_wand: {S.shape[1]} sensors but the wand calibration has {len(wand.positions)}")
    F = len(S)
    r, T = np.array(position0, float), np.array(rotation0, float)
    if r.shape != (F, 3) or T.shape != (F, 3, 3):
        raise InputError(f"solve_wand: starting poses must be ({F}, 3) and ({F}, 3, 3), got {r.shape} and {T.shape}")
    use = use & dipole.usable_signals(S)
    S = np.where(use[..., None, None], S, 0.0)
    scale = np.where(use, np.sqrt(np.mean(S**2, axis=(-1, -2))), 1.0)
    active = use.any(axis=1) & np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(T.reshape(F, 9)), axis=1)
    r[~active], T[~active] = (1.0, 0.0, 0.0), np.eye(3)  # a harmless placeholder, never stepped
    return S, use, scale, r, T, active


def _wand_solution(r, T, converged, active, use, cost, H) -> WandSolution:
    """Residuals and standard errors from the final cost (F,) and JᵀJ (F, 6, 6) of each frame."""
    F = len(r)
    used = use.sum(axis=1)
    residual = np.sqrt(cost / np.maximum(9 * used, 1))
    H = H.copy()
    H[~active] = np.eye(6)
    H[~np.all(np.isfinite(H.reshape(F, -1)), axis=1)] = np.eye(6)
    with np.errstate(invalid="ignore", divide="ignore"):
        dof = np.maximum(9 * used - 6, 1)
        covariance = np.linalg.pinv(H) * (cost / dof)[:, None, None]
    position_sigma = np.sqrt(np.trace(covariance[:, :3, :3], axis1=1, axis2=2))
    angle_sigma = np.sqrt(np.trace(covariance[:, 3:, 3:], axis1=1, axis2=2))
    r[~active], T[~active] = np.nan, np.nan
    converged = converged & active
    return WandSolution(r, T, converged, residual, position_sigma, angle_sigma, use)


def solve_wand_table(S: np.ndarray, use: np.ndarray, wand: WandCalibration, table: GridField, position0: np.ndarray,
                     rotation0: np.ndarray, max_iterations: int = 40, step_tolerance: float = 1e-10) -> WandSolution:
    """:func:`solve_wand` compiled (``ivc.lut.joint_kernels``, parallel over frames) for a look-up table's
    field: the same problem, inputs and result, without the NumPy form's per-chunk (F, W, 9, 6) arrays."""
    from ivc.lut.joint_kernels import wand_kernel
    from ivc.lut.rigid_kernels import Limits, Wand

    if not isinstance(table, GridField):
        raise InputError(f"solve_wand_table needs a GridField, got {type(table).__name__}")
    S, use, scale, r, T, active = _prepare(S, use, wand, position0, rotation0)
    F = len(S)
    converged = np.zeros(F, dtype=bool)
    cost, H = np.zeros(F), np.zeros((F, 6, 6))
    wand_kernel(np.ascontiguousarray(S), np.ascontiguousarray(use), np.ascontiguousarray(scale),
                Wand(np.ascontiguousarray(wand.positions, dtype=float),
                     np.ascontiguousarray(wand.rotations, dtype=float)),
                table.kernel_grid, Limits(int(max_iterations), float(step_tolerance)), active, r, T, converged, cost, H)
    return _wand_solution(r, T, converged, active, use, cost, H)


def seed_from_sensors(correction_position: np.ndarray, correction_quaternion: np.ndarray, trusted: np.ndarray,
                      residual: np.ndarray, wand: WandCalibration) -> tuple[np.ndarray, np.ndarray]:
    """Sensor 0's pose (F, 3), (F, 3, 3) from the best-explained trusted sensor of each frame: ``T_0 = T_n R_nᵀ``,
    ``r_0 = r_n − T_0 b_n`` (the wand calibration inverted); NaN where no sensor is trusted."""
    F = len(trusted)
    score = np.where(trusted, residual, np.inf)
    best = np.argmin(score, axis=1)
    rows = np.arange(F)
    T_n = rotations.to_matrix(np.where(trusted[rows, best, None], correction_quaternion[rows, best], [1.0, 0, 0, 0]))
    T0 = T_n @ np.swapaxes(wand.rotations[best], -1, -2)
    r0 = correction_position[rows, best] - np.einsum("fij,fj->fi", T0, wand.positions[best])
    none = ~trusted.any(axis=1)
    r0[none], T0[none] = np.nan, np.nan
    return r0, T0


@dataclass
class JointOptions:
    """``spacing``: table grid spacing (m). ``min_support``: samples around a node for it to be mapped.
    ``max_iterations``: rounds of re-solve and refit. ``tolerance``: stop when the map changes by less
    than this (pose-equivalent RMS over the nodes mapped before, m) and the mapped volume grows by less
    than ``min_growth`` (fraction); or when it grows by less than ``stall_growth`` (fraction) whatever its
    change (on the cockpit scene the change stays at millimetres, carried by the edge nodes, while the
    volume stops growing: further rounds cost time and add nothing). ``max_residual``: a re-solved
    frame's relative residual gate.
    ``max_error``: a sample's estimated error gate (m, eq. 101 with the rigid solve's standard errors).
    ``max_frames``: the cube sweep decimated to this many frames; ``max_extension_frames``: each
    extension sweep decimated to this many. ``min_sensors``: mapped sensors a frame needs to be solved.
    ``source_standoff``, ``source_spacing``: the inner shell of equivalent sources, beyond the samples'
    bounding box (m): farther out than the table's outermost nodes (up to 1.5 cells beyond the data), so
    that no node is tabulated next to a source, and about where the metal of a cockpit is. ``dampings``: the
    Tikhonov dampings the cross-validation of the first and the final fit chooses from (the rounds between
    keep the first fit's). ``table_subdivision``: the table is tabulated this many times finer than
    ``spacing`` (support and validity stay those of the ``spacing`` cells, :func:`subdivided`): cubic
    interpolation of the field between nodes 38 mm apart, 9 cm from a panel, costs more than the map's
    own error at the box's faces. ``even_cell``: beyond the sources fit's sample cap, the samples fitted are
    spread evenly over cubes of this size (m; :func:`ivc.lut.fit_sources.even_subset`), not every k-th
    (None): every k-th keeps the cube sweep's dense ball and thins the far faces alike. ``error_floor``: the
    ``ε_0`` (m) of the samples' weights ``λ² / (ε² + ε_0²)`` in every sources fit of the joint solve.
    ``max_samples``: the samples each sources fit uses at most (its cost grows with them; beyond it they are
    thinned as ``even_cell`` says)."""

    spacing: float = DEFAULT_SPACING
    min_support: int = MIN_SUPPORT
    max_iterations: int = 6
    tolerance: float = 5e-6
    min_growth: float = 0.01
    stall_growth: float = 0.02
    max_residual: float = 1e-3
    max_error: float = 1e-3
    max_frames: int = 25_000
    max_extension_frames: int = 5_000
    min_sensors: int = 2
    source_standoff: float = SOURCE_STANDOFF
    source_spacing: float = SPACING
    dampings: tuple = DAMPINGS
    table_subdivision: int = TABLE_SUBDIVISION
    even_cell: float | None = EVEN_CELL
    error_floor: float = ERROR_FLOOR
    max_samples: int = MAX_SAMPLES

    def __post_init__(self):
        check_max_samples(self.max_samples)
        self.dampings = tuple(float(d) for d in self.dampings)
        if not self.dampings or not all(np.isfinite(d) and d > 0 for d in self.dampings):
            raise InputError(f"dampings must be positive numbers, got {self.dampings!r}")
        if self.even_cell is not None and not (np.isfinite(self.even_cell) and self.even_cell > 0):
            raise InputError(f"even_cell must be a positive number of metres or None, got {self.even_cell!r}")
        if not (np.isfinite(self.stall_growth) and self.stall_growth >= 0):
            raise InputError(f"stall_growth must be a fraction of at least 0, got {self.stall_growth}")
        for name in ("spacing", "tolerance", "max_residual", "max_error", "source_standoff", "source_spacing",
                     "error_floor"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"{name} must be a positive number, got {value}")
        for name in ("min_support", "max_iterations", "max_frames", "max_extension_frames", "min_sensors",
                     "table_subdivision"):
            value = getattr(self, name)
            if not isinstance(value, int | np.integer) or value < 1:
                raise InputError(f"{name} must be a whole number of at least 1, got {value!r}")


@dataclass
class JointMap:
    """The result of :func:`fit_joint`: the field ``model`` over the volume, its ``grid``, node ``values``
    (nx, ny, nz, 3, 3), ``valid`` and ``support`` (nx, ny, nz), the ``samples`` it was fitted to, the
    per-sweep ``solutions`` of the last round and a ``report`` (json-ready)."""

    model: SourceModel
    grid: Grid
    values: np.ndarray
    valid: np.ndarray
    support: np.ndarray
    samples: FieldSamples
    solutions: dict
    report: dict


def to_table(joint: JointMap, hemisphere: str, provenance: dict | None = None) -> LookupTable:
    """The joint map as a look-up table (the file ``ivc correct`` reads)."""
    return LookupTable(joint.grid, joint.values, joint.valid, joint.support, hemisphere, joint.report,
                       provenance or {})


def _noop(desc: str, total: int) -> Callable[[int], None]:
    return lambda n: None


def subdivided(grid: Grid, valid: np.ndarray, support: np.ndarray, subdivision: int
               ) -> tuple[Grid, np.ndarray, np.ndarray]:
    """The grid with every cell cut into ``subdivision``³ cells, and each fine node's validity and support:
    a fine node is valid when every coarse node of the smallest coarse cell, face, edge or node that holds
    it is valid, and its support is the least of theirs. The mapped volume (cells whose eight corners are
    valid) is the coarse one, so the validity stays the coarse cells' support test."""
    if subdivision == 1:
        return grid, valid, support
    fine = Grid(grid.origin, grid.spacing / subdivision, tuple((n - 1) * subdivision + 1 for n in grid.shape))
    lows = [np.arange(n) // subdivision for n in fine.shape]
    highs = [-(-np.arange(n) // subdivision) for n in fine.shape]
    fine_valid = np.ones(fine.shape, dtype=bool)
    fine_support = np.full(fine.shape, np.iinfo(np.int64).max, dtype=np.int64)
    for ix in (lows[0], highs[0]):
        for iy in (lows[1], highs[1]):
            for iz in (lows[2], highs[2]):
                index = np.ix_(ix, iy, iz)
                fine_valid &= valid[index]
                fine_support = np.minimum(fine_support, support[index])
    return fine, fine_valid, fine_support


def tabulate(model: SourceModel, positions: np.ndarray, spacing: float, min_support: int, subdivision: int = 1):
    """The model on the grid around the samples' ``positions`` (N, 3) m: node support counted on the ``spacing``
    grid, the table ``subdivision`` times finer (:func:`subdivided`)."""
    grid = Grid.around(positions, spacing)
    support = node_support(grid, positions)
    grid, valid, support = subdivided(grid, support >= min_support, support, subdivision)
    values = model(grid.nodes())
    return grid, values, valid, support


def mapped_litres(grid: Grid, valid: np.ndarray) -> float:
    """Volume (litres) of the cells whose eight corners are mapped."""
    v = valid
    cells = (v[:-1, :-1, :-1] & v[1:, :-1, :-1] & v[:-1, 1:, :-1] & v[:-1, :-1, 1:] & v[1:, 1:, :-1]
             & v[1:, :-1, 1:] & v[:-1, 1:, 1:] & v[1:, 1:, 1:])
    return float(cells.sum() * grid.spacing**3 * 1000)


def _change(model: SourceModel, grid: Grid, values: np.ndarray, valid: np.ndarray) -> float:
    """Pose-equivalent RMS change (m) of the new ``model`` against the previous table's valid nodes."""
    nodes = grid.nodes()[valid]
    if len(nodes) == 0:
        return float("inf")
    change = leverage(nodes) * np.linalg.norm(model(nodes) - values[valid], axis=(1, 2))
    return float(np.sqrt(np.mean(change**2)))


def extension_samples(S: np.ndarray, valid: np.ndarray, wand: WandCalibration, table: GridField, hemisphere: str,
                      options: JointOptions, frame_offset: int) -> tuple[FieldSamples, WandSolution, np.ndarray]:
    """One extension sweep against the current table: each sensor corrected, frames with at least
    ``min_sensors`` trusted sensors solved as a rigid wand from them, gated, and every valid sensor of a
    kept frame turned into a sample. Returns the samples, the solution and the kept frames (F,)."""
    corrected = Corrector(table, hemisphere, max_residual=options.max_residual).batch(S, valid)
    trusted = (corrected.flags == 0) & valid
    solvable = trusted.sum(axis=1) >= options.min_sensors
    r0, T0 = seed_from_sensors(corrected.position, corrected.quaternion, trusted & solvable[:, None],
                               corrected.residual, wand)
    solution = solve_wand_table(S, trusted & solvable[:, None], wand, table, r0, T0)
    positions, rots = wand.propagate(np.where(solution.converged[:, None], solution.position, 0.0),
                                     np.where(solution.converged[:, None, None], solution.rotation, np.eye(3)))
    still_mapped = table.mapped(positions) | ~solution.used  # the constraining sensors stay in the map
    kept = (solution.converged & solvable & (solution.residual <= options.max_residual) & still_mapped.all(axis=1))
    error = solution.position_sigma[:, None] + wand.lever_arms[None, :] * np.tan(solution.angle_sigma)[:, None]
    keep = kept[:, None] & valid & (error <= options.max_error)
    frame, sensor = np.nonzero(keep)
    fields = rots[frame, sensor] @ S[frame, sensor] - dipole.field(positions[frame, sensor])
    samples = FieldSamples(positions[frame, sensor], fields, error[frame, sensor], frame + frame_offset, sensor)
    return samples, solution, kept


def extension_part(session: Session, name: str, wand: WandCalibration, max_frames: int,
                   stride: int | None = None) -> tuple[Step, int]:
    """Extension sweep ``name`` of ``session``, checked against the ``wand`` calibration, as solved: every
    ``stride``-th frame (default: the fewest that keep at most ``max_frames``). Returns the frames and the stride."""
    step = session.steps[name]
    if step.n_sensors != len(wand.positions):
        raise SessionError(f"/steps/{name}: {step.n_sensors} sensors but the wand calibration has "
                           f"{len(wand.positions)}")
    stride = max(1, int(stride or -(-step.n_frames // max_frames)))
    return step.select(slice(None, None, stride)), stride


def _concatenate(parts: list[FieldSamples]) -> FieldSamples:
    return FieldSamples(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                          ("positions", "fields", "error", "frame", "sensor")))


def distance_profile(samples: FieldSamples, centre: np.ndarray, bins: int = 5) -> list[dict]:
    """Estimated sample error (eq. 101 with the solve's standard errors) against distance from the cube's
    centre, in ``bins`` equal ranges of distance: median and 95th percentile in mm."""
    distance = np.linalg.norm(samples.positions - centre, axis=1)
    edges = np.linspace(0.0, distance.max() * (1 + 1e-9), bins + 1)
    rows = []
    for low, high in zip(edges[:-1], edges[1:], strict=True):
        inside = (distance >= low) & (distance < high)
        if inside.any():
            rows.append({"from_mm": 1000 * low, "to_mm": 1000 * high, "samples": int(inside.sum()),
                         "error_p50_mm": 1000 * float(np.median(samples.error[inside])),
                         "error_p95_mm": 1000 * float(np.percentile(samples.error[inside], 95))})
    return rows


def _sources(samples: FieldSamples, options: JointOptions) -> np.ndarray:
    return default_sources(samples.positions, options.source_standoff, options.source_spacing)


def fit_joint(session: Session, options: JointOptions | None = None, progress=None) -> JointMap:
    """The whole-volume map of a session with extension sweeps (module docstring). ``progress(description,
    total)`` returns an update callback per stage, as :func:`ivc.lut.build.fit_lut`'s."""
    options = options or JointOptions()
    progress = progress or _noop
    names = extension_steps(session.steps)
    if not names:
        raise SessionError("the session has no extension sweeps (extension_sweep_1, ...): `ivc fit` maps the "
                           "region around the cube alone; record extension sweeps with `ivc collect "
                           "extension_sweep_1` to map more")
    missing = session.missing_for_fit()
    if missing:
        raise SessionError("cannot fit a map; the session is missing:\n  " + "\n  ".join(missing))
    model = FixtureModel.from_session(session)
    stride = max(1, -(-session.steps["wand_sweep"].n_frames // options.max_frames))
    if stride > 1:
        session = session.select_frames("wand_sweep", slice(None, None, stride))
    sweep = session.steps["wand_sweep"]
    gates = Gates(max_residual=options.max_residual, max_error=options.max_error)
    mapping = map_sweep(session, model, gates, progress=progress("solving the sweep in the cube", sweep.n_frames))
    anchor = FieldSamples.from_mapping(mapping)
    if len(anchor) < 2_000:
        raise SessionError(f"only {len(anchor)} cube-sweep samples passed the gates: check `ivc fixtures`")
    extensions = {}
    for number, name in enumerate(names, start=1):
        part, every = extension_part(session, name, model.wand, options.max_extension_frames)
        extensions[name] = (part.signal_matrices(), part.valid_mask, number * FRAME_OFFSET, every)
    centre = model.placement.positions.mean(axis=0)
    bar = progress("fitting equivalent sources (cross-validated)", len(anchor))
    field, fit = fit_sources(anchor, _sources(anchor, options), options.dampings, max_samples=options.max_samples,
                             progress=bar, even_cell=options.even_cell, error_floor=options.error_floor)
    damping = fit["damping"]
    samples = anchor
    grid, values, valid, support = tabulate(field, samples.positions, options.spacing, options.min_support,
                                               options.table_subdivision)
    history = [{"iteration": 0, "samples": len(samples), "mapped_litres": mapped_litres(grid, valid),
                "map_change_mm": None, "frames_solved": {name: 0 for name in names}}]
    solutions, stopped, normal = {}, None, None
    for iteration in range(1, options.max_iterations + 1):
        table = GridField(grid, values, valid)
        parts, solved = [anchor], {}
        for name, (S, ok, offset, _) in extensions.items():
            found, solution, kept = extension_samples(S, ok, model.wand, table, session.hemisphere, options, offset)
            parts.append(found)
            solved[name] = int(kept.sum())
            solutions[name] = (solution, kept)
        samples = _concatenate(parts)
        bar = progress(f"round {iteration}: refit", len(samples))
        normal = normal_equations(samples, _sources(samples, options), max_samples=options.max_samples, progress=bar,
                                  even_cell=options.even_cell, error_floor=options.error_floor)
        field, _ = solve_normal_equations(normal, (damping,))
        change = _change(field, grid, values, valid)
        before = mapped_litres(grid, valid)
        grid, values, valid, support = tabulate(field, samples.positions, options.spacing, options.min_support,
                                               options.table_subdivision)
        litres = mapped_litres(grid, valid)
        history.append({"iteration": iteration, "samples": len(samples), "mapped_litres": litres,
                        "map_change_mm": 1000 * change, "frames_solved": solved})
        if change < options.tolerance and litres < (1 + options.min_growth) * before:
            stopped = (f"the map changed by less than {1e6 * options.tolerance:g} µm and grew by less than "
                       f"{100 * options.min_growth:g} %")
            break
        if litres < (1 + options.stall_growth) * before:
            stopped = f"the mapped volume grew by less than {100 * options.stall_growth:g} % (it has stopped growing)"
            break
    stopped = stopped or f"max_iterations {options.max_iterations} reached"
    # the last round's samples: its normal equations, cross-validated
    field, fit = solve_normal_equations(normal, options.dampings)
    grid, values, valid, support = tabulate(field, samples.positions, options.spacing, options.min_support,
                                               options.table_subdivision)
    never = [name for name in names if all(step["frames_solved"].get(name, 0) == 0 for step in history)]
    report = {"method": "equivalent sources, joint", **fit, "rounds": history, "stopped": stopped,
              "extension_sweeps": {name: {"frames_used": len(extensions[name][0]), "stride": extensions[name][3],
                                          "frames_solved": history[-1]["frames_solved"].get(name, 0)}
                                   for name in names},
              "never_touched_mapped_region": never, "mapped_litres": mapped_litres(grid, valid),
              "error_by_distance": distance_profile(samples, centre),
              "cube_centre": centre.tolist(), "samples": {"anchor": len(anchor), "total": len(samples)},
              "valid_nodes": int(valid.sum()), "min_support": options.min_support,
              "support_spacing_m": options.spacing, "table_subdivision": options.table_subdivision,
              "sample_selection": "even" if options.even_cell is not None else "stride",
              "max_samples": options.max_samples,
              "frames": {"recorded": mapping.keep.shape[0] * stride, "used": sweep.n_frames, "stride": stride}}
    return JointMap(field, grid, values, valid, support, samples, solutions, report)


def fit_joint_lut(session: Session, options=None, source=None, progress=None) -> LookupTable:
    """:func:`fit_joint` as ``ivc fit`` runs it on a session with extension sweeps: the grid spacing,
    support, gates and cube-sweep decimation from ``options`` (:class:`ivc.lut.options.FitOptions`; its
    fitter and refinement do not apply: the map is always equivalent sources, re-solved jointly)."""
    options = options or FitOptions()
    joint = fit_joint(session, JointOptions(spacing=options.spacing, min_support=options.min_support,
                                            max_residual=options.max_residual, max_error=options.max_error,
                                            max_frames=options.max_frames), progress)
    report = joint.report
    anchor, total = report["samples"]["anchor"], report["samples"]["total"]
    report["samples"] = {"total": total, "kept": total, "used": total, "anchor": anchor, "outside_grid": 0,
                         "dropped": {}}
    report.update(refinement=[], grid_from="data (one-cell margin)")
    parameters = {"spacing": options.spacing, "min_support": options.min_support, "max_residual": options.max_residual,
                  "max_error": options.max_error, "max_frames": options.max_frames}
    return to_table(joint, session.hemisphere, provenance(parameters, source))
