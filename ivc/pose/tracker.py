"""Sensor pose in free space with a calibrated tracker model (docs/tracker.md).

The solve minimises ``‖S − S_model(r, T)‖_F`` over position and a rotation increment
``T ← T exp([ω]×)`` by Levenberg-Marquardt, every frame of the batch stepping together
(:func:`ivc.pose.solver.levenberg_marquardt`). What makes it hold on any coil geometry is
the gate and the start the retry takes:

- **First pass.** The closed-form dipole pose of the gain-corrected signal
  ``B⁻ᵀ (S − bias) A⁻¹`` is the start: exact for concentric coils without noise, but with
  coils tens of millimetres off-centre it can be 100 degrees off and the solve from it can
  end in a wrong minimum.
- **Gate.** A frame has *converged* only when the solve converged and its relative
  residual ``‖S − S_model‖_F / ‖S‖_F`` is within the model's own gate
  (:meth:`Tracker.pose_gate`: the calibration's residue distribution, and the signal noise
  when the caller knows it). A wrong minimum leaves a residual of percent against the
  model's tenths, so it fails.
- **Retry, from a start that knows the coil geometry.** A frame that fails the gate is
  solved again from the best points of a search over positions on its side, each with
  the orientation that is best there in closed form (:func:`_grid_starts`), then from a
  few more starts (half turns about each axis, nearer and farther, the other
  hemisphere's closed form); a pose that passes, else the lowest residual on the declared
  side, is kept. Only the frames that still fail are tried again.
- **Only where a wrong minimum is possible.** Next to metal every frame fails the gate: its
  residual holds the room's field, not a wrong minimum. A failing frame whose first pass
  already sits at the search's best start (:func:`_same_start`), with coils less than
  :data:`NEAR_RATIO` of the range off-centre, keeps its pose: no start is better, and the
  retry would find the same minimum nine times over (measured on a room with a plate: it
  changed no pose, and took 90 % of the conversion's time).

The ideal tracker gives the closed-form pose itself, bit for bit. A tracker's output
correction, if it has one, is applied last, to every frame.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from ivc import rotations
from ivc.dipole import closed_form_pose, hemisphere_vector
from ivc.dipole.tracker import Tracker
from ivc.errors import InputError
from ivc.pose.solver import PoseSolution, levenberg_marquardt, procrustes, procrustes_cost

__all__ = ["GRID_DIRECTIONS", "GRID_RANGES", "GRID_SEPARATION_DEG", "GRID_STARTS", "IdealSignals", "ideal_signals",
           "noise_gain", "to_ideal", "tracker_pose"]

#: the start search of a frame that fails the gate: directions on its half sphere, ranges (fractions of
#: the dipole range of its signal), and how far apart (degrees) the starts it keeps must be
GRID_DIRECTIONS = 128
GRID_RANGES = (0.75, 0.85, 0.95, 1.05, 1.15, 1.3)
GRID_SEPARATION_DEG = 25.0
GRID_STARTS = 3
_GRID_CHUNK = 1024
#: the most a failing pose may be turned from the search's best start and still be taken as its minimum
SAME_START_DEG = 45.0
#: coil offsets (the farthest coil centre from its coil set's origin) above this fraction of the range: a wrong
#: minimum can sit at the search's best start itself (seen from 0.22 on, simulated 20-60 mm sources at
#: 0.03-0.3 m), so a failing frame there is retried from every start whatever its first pass
NEAR_RATIO = 0.15
_FAR = 100.0  # m: a trial position beyond this has run off (the field there is nothing)


def _directions(hemisphere: str | ArrayLike | None, tracker: Tracker, frames: int) -> np.ndarray:
    if hemisphere is None:
        hemisphere = tracker.hemisphere if tracker.hemisphere is not None else "+x"
    if isinstance(hemisphere, str):
        return np.broadcast_to(hemisphere_vector(hemisphere), (frames, 3))
    h = np.asarray(hemisphere, dtype=float)
    if h.shape not in ((3,), (frames, 3)):
        raise InputError(f"hemisphere must be a name like '+x', a vector (3,) or vectors (F, 3); got {h.shape}")
    return np.broadcast_to(h, (frames, 3))


def _refine(S: np.ndarray, tracker: Tracker, r: np.ndarray, T: np.ndarray, idx: np.ndarray, max_iterations: int,
            step_tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt on frames ``idx`` of (r, T), updated in place; their convergence, iterations,
    residuals (len, 9) and Jacobian (len, 9, 6)."""

    def residual(rows, r_, T_):
        with np.errstate(all="ignore"):
            Sm, dS = tracker.pose_jacobian(r_, T_)
            e_, J_ = (S[rows] - Sm).reshape(len(rows), 9), -dS.reshape(len(rows), 9, 6)
        scale = np.linalg.norm(S[rows].reshape(len(rows), 9), axis=1)
        wild = ~(np.all(np.isfinite(e_), axis=1) & np.all(np.isfinite(J_), axis=(1, 2))
                 & (np.linalg.norm(r_, axis=1) < _FAR) & (np.abs(J_).max(axis=(1, 2)) > 1e-12 * scale))
        e_[wild], J_[wild] = np.inf, np.eye(9, 6)  # at a coil's centre or run off to infinity: never accepted
        return e_, J_

    r_i, T_i = r[idx].copy(), T[idx].copy()
    e, J = residual(idx, r_i, T_i)

    def trial(rows, step):
        r_t = r_i[rows] + step[:, :3]
        T_t = T_i[rows] @ rotations.to_matrix(rotations.from_rotvec(step[:, 3:]))
        return (r_t, T_t), *residual(idx[rows], r_t, T_t)

    converged, iterations = levenberg_marquardt((r_i, T_i), e, J, np.all(np.isfinite(e), axis=1), trial,
                                                max_iterations, step_tolerance)
    r[idx], T[idx] = r_i, T_i
    return converged, iterations, e, J


def _relative(e: np.ndarray, S: np.ndarray) -> np.ndarray:
    return np.linalg.norm(e, axis=-1) / np.linalg.norm(S.reshape(len(S), 9), axis=-1)


def _hemisphere_directions(count: int) -> np.ndarray:
    """``count`` unit vectors spread evenly over the half sphere ``z >= 0`` (a Fibonacci lattice)."""
    k = np.arange(count) + 0.5
    z = k / count
    phi = np.pi * (1.0 + np.sqrt(5.0)) * k
    rho = np.sqrt(1.0 - z**2)
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)


_DIRECTIONS = _hemisphere_directions(GRID_DIRECTIONS)


def _turn_to(h: np.ndarray) -> np.ndarray:
    """Rotations (F, 3, 3) taking +z to each unit vector of ``h`` (F, 3)."""
    h = h / np.linalg.norm(h, axis=1, keepdims=True)
    helper = np.where((np.abs(h[:, 0]) < 0.9)[:, None], np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    x = np.cross(helper, h)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return np.stack([x, np.cross(h, x), h], axis=2)


def _grid_starts(S: np.ndarray, tracker: Tracker, h: np.ndarray, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The ``count`` best distinct starts (r, T) of each frame from a search over positions on its side.

    With the sensor coils taken at their centroid, ``S ≈ Bᵀ Tᵀ M(r) + bias`` where column ``i``
    of ``M(r)`` is source coil ``i``'s field ``f_D(r − p_i) a_i`` at ``r``: at a given position
    the best orientation is the Procrustes rotation of ``M(r)`` onto ``B⁻ᵀ (S − bias)``. The
    residual left (:func:`ivc.pose.solver.procrustes_cost`, no rotation formed) is searched over
    :data:`GRID_DIRECTIONS` directions on the declared half sphere times the ranges
    :data:`GRID_RANGES` of the range the signal's size gives, and the best points at least
    :data:`GRID_SEPARATION_DEG` apart are returned, best first, with their Procrustes rotations.
    Frames are searched :data:`_GRID_CHUNK` at a time (the search holds K positions per frame).
    """
    F, K = len(S), len(_DIRECTIONS)
    Sg = np.linalg.inv(tracker.sensor_moments).T @ (S - tracker.bias)
    distance = (6.0 / np.sum(tracker.corrected(S) ** 2, axis=(1, 2))) ** (1.0 / 6.0)
    directions = np.einsum("fab,kb->fka", _turn_to(h), _DIRECTIONS)  # (F, K, 3)
    best_cost = np.full((F, K), np.inf)
    best_scale = np.zeros((F, K))
    p, A = tracker.source_offsets, tracker.source_moments

    def coil_fields(r):  # (..., 3) -> M (..., 3, 3), column i = f_D(r − p_i) a_i (eq. 72 times the moment)
        x = r[..., None, :] - p  # (..., i, 3)
        d2 = np.sum(x * x, axis=-1, keepdims=True)
        with np.errstate(divide="ignore", invalid="ignore"):
            columns = (3.0 * x * (np.sum(x * A.T, axis=-1, keepdims=True) / d2) - A.T) / (d2 * np.sqrt(d2))
        return np.swapaxes(columns, -1, -2)

    for lo in range(0, F, _GRID_CHUNK):
        rows = slice(lo, lo + _GRID_CHUNK)
        for scale in GRID_RANGES:
            r = directions[rows] * (scale * distance[rows])[:, None, None]
            cost = procrustes_cost(coil_fields(r), Sg[rows, None])
            better = cost < best_cost[rows]
            best_cost[rows] = np.where(better, cost, best_cost[rows])
            best_scale[rows] = np.where(better, scale, best_scale[rows])
    out = []
    cos_limit = np.cos(np.radians(GRID_SEPARATION_DEG))
    frames = np.arange(F)
    for _ in range(count):
        k = np.argmin(best_cost, axis=1)
        r = directions[frames, k] * (best_scale[frames, k] * distance)[:, None]
        out.append((r, procrustes(coil_fields(r), Sg)))
        near = np.einsum("fka,fa->fk", directions, directions[frames, k]) > cos_limit
        best_cost[near] = np.inf
    return out


def _same_start(r: np.ndarray, T: np.ndarray, r_s: np.ndarray, T_s: np.ndarray) -> np.ndarray:
    """Whether each pose (r, T) is the start (r_s, T_s) of the search's cell it lies in: positions apart by at
    most the chord of :data:`GRID_SEPARATION_DEG` relative to the range, orientations by at most
    :data:`SAME_START_DEG`."""
    apart = np.linalg.norm(r - r_s, axis=1) / np.linalg.norm(r, axis=1)
    turned = rotations.angle_between_matrices(T, T_s)
    return (apart <= 2.0 * np.sin(np.radians(GRID_SEPARATION_DEG) / 2.0)) & (turned <= np.radians(SAME_START_DEG))


def _candidates(r: np.ndarray, T: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Other starts near a pose: the orientation turned half a turn about each of its axes, the
    position nearer and farther."""
    out = []
    for axis in range(3):
        turn = rotations.to_matrix(rotations.from_rotvec(np.pi * np.eye(3)[axis]))
        out.append((r.copy(), T @ turn))
    for scale in (0.8, 1.25):
        out.append((scale * r, T.copy()))
    return out


def _solve(S: np.ndarray, tracker: Tracker, h: np.ndarray, gate: float, max_iterations: int, step_tolerance: float,
           retry: bool, start):
    """Poses of finite frames S (F, 3, 3) under the full model; returns r, T, converged (LM), passed (gate),
    iterations, residual (F,) and the last residuals and Jacobian."""
    F = len(S)
    r0, T0 = closed_form_pose(tracker.corrected(S), "+x")
    flip = np.einsum("fi,fi->f", r0, h) < 0
    r0[flip] = -r0[flip]
    r, T = (r0.copy(), T0.copy()) if start is None else (start[0].copy(), start[1].copy())
    full = replace(tracker, position_correction=np.zeros((3, 4)), rotation_correction=np.zeros((3, 4)))
    converged, iterations, e, J = _refine(S, full, r, T, np.arange(F), max_iterations, step_tolerance)
    residual = _relative(e, S)

    def attempt(bad, r_s, T_s):
        """Solve frames ``bad`` again from (r_s, T_s); keep a pose that passes where the last did not, or
        that lowers the residual."""
        r_c, T_c = r.copy(), T.copy()
        r_c[bad], T_c[bad] = r_s, T_s
        conv_c, its_c, e_c, J_c = _refine(S, full, r_c, T_c, bad, max_iterations, step_tolerance)
        iterations[bad] += its_c
        res_c = _relative(e_c, S[bad])
        side = np.einsum("fi,fi->f", r_c[bad], h[bad]) >= 0
        ok_c, ok = conv_c & (res_c <= gate), converged[bad] & (residual[bad] <= gate)
        better = side & np.isfinite(res_c) & ((ok_c & ~ok) | ((ok_c == ok) & (res_c < residual[bad])))
        take = bad[better]
        r[take], T[take] = r_c[take], T_c[take]
        converged[take], residual[take] = conv_c[better], res_c[better]
        e[take], J[take] = e_c[better], J_c[better]

    def failing():
        return np.flatnonzero(~(converged & (residual <= gate)))

    if retry:
        # the search's best start says where the wrong minimum a failing frame may sit in is possible: a frame
        # whose first pass is already that start's pose (:func:`_same_start`) has nothing better to go to, and
        # its residual is what the signal holds beyond the model (a room's field, noise): it keeps its pose
        planned = failing()
        grid = _grid_starts(S[planned], tracker, h[planned], GRID_STARTS) if len(planned) else []
        if len(planned):
            reach = max(np.linalg.norm(tracker.source_offsets, axis=1).max(),
                        np.linalg.norm(tracker.sensor_offsets, axis=1).max())
            near = reach > NEAR_RATIO * np.linalg.norm(r[planned], axis=1)
            doubt = near | ~_same_start(r[planned], T[planned], *grid[0])
            planned, grid = planned[doubt], [(r_s[doubt], T_s[doubt]) for r_s, T_s in grid]
        for plan in range(2):  # each start only for the frames that still fail, until none does
            if plan == 1:
                planned = planned[np.isin(planned, failing())]
                grid = _candidates(r[planned], T[planned]) + [(-r0[planned], T0[planned])] if len(planned) else []
            for r_s, T_s in grid:
                still = np.isin(planned, failing())
                if not still.any():
                    break
                attempt(planned[still], r_s[still], T_s[still])
    passed = residual <= gate
    return r, T, converged, passed, iterations, residual, e, J


def tracker_pose(S: ArrayLike, tracker: Tracker | None = None, hemisphere: str | ArrayLike | None = None, *,
                 max_iterations: int = 50, step_tolerance: float = 1e-10, correct: bool = True,
                 noise_relative: float = 0.0, gate: float | None = None, retry: bool = True,
                 start: tuple[ArrayLike, ArrayLike] | None = None) -> PoseSolution:
    """Poses of free-space signal matrices ``S`` (F, 3, 3) under ``tracker`` (None: ideal).

    ``hemisphere``: a declared side (``"+x"``, ...), or a direction (3,) or one per frame
    (F, 3), in the source frame; the position is taken on its side. None: the side the
    tracker's calibration recorded (:attr:`Tracker.hemisphere`), else ``"+x"``.
    Returns a :class:`ivc.pose.solver.PoseSolution` (position metres, source frame;
    ``residual`` is ``‖S − S_model‖_F / ‖S‖_F``). ``converged`` is True only for a frame whose
    solve converged *and* whose residual is within ``gate`` (default :meth:`Tracker.pose_gate`
    of the tracker and ``noise_relative``, the signals' per-entry noise relative to ``‖S‖₂``
    where known): a wrong minimum is never called converged. ``retry``: solve frames that
    fail from other starts (module docstring). ``start``: positions (F, 3) m and orientations
    (F, 3, 3) to start the first pass from instead of the closed form (a previous frame's pose;
    the true pose, for a noise floor). Frames with non-finite signals come back
    NaN, not converged. ``correct``: apply the tracker's output correction
    (:meth:`ivc.dipole.tracker.Tracker.correct_pose`), if it has one.
    """
    S = np.asarray(S, dtype=float)
    if S.ndim != 3 or S.shape[1:] != (3, 3):
        raise InputError(f"S must have shape (F, 3, 3), got {S.shape}")
    F = len(S)
    tracker = Tracker.ideal() if tracker is None else tracker
    h = _directions(hemisphere, tracker, F)
    finite = np.all(np.isfinite(S.reshape(F, -1)), axis=1)
    S = np.where(finite[:, None, None], S, np.eye(3))  # placeholders, never reported
    zeros = np.zeros(F)
    if tracker.is_ideal:
        r, T = closed_form_pose(S, "+x")
        flip = np.einsum("fi,fi->f", r, h) < 0
        r[flip] = -r[flip]
        r[~finite], T[~finite] = np.nan, np.nan
        return PoseSolution(r, T, finite.copy(), np.zeros(F, dtype=int), zeros, zeros.copy(), zeros.copy())
    gate = tracker.pose_gate(noise_relative) if gate is None else float(gate)
    if start is not None:
        start = (np.asarray(start[0], dtype=float), np.asarray(start[1], dtype=float))
        if start[0].shape != (F, 3) or start[1].shape != (F, 3, 3):
            raise InputError(f"start must be positions (F, 3) and rotations (F, 3, 3) for F = {F}; got "
                             f"{start[0].shape} and {start[1].shape}")
        start = (np.where(finite[:, None], start[0], 1.0), np.where(finite[:, None, None], start[1], np.eye(3)))
    r, T, converged, passed, iterations, rel, e, J = _solve(S, tracker, h, gate, max_iterations, step_tolerance,
                                                            retry, start)
    sigma2 = np.sum(e**2, axis=1) / 3.0
    with np.errstate(invalid="ignore"):
        cov = np.linalg.pinv(np.einsum("fki,fkj->fij", J, J)) * sigma2[:, None, None]
        diag = np.einsum("fii->fi", cov)
        pos_sigma, ang_sigma = np.sqrt(diag[:, :3].sum(axis=1)), np.sqrt(diag[:, 3:].sum(axis=1))
    if correct:
        r, T = tracker.correct_pose(r, T)
    r[~finite], T[~finite] = np.nan, np.nan
    rel[~finite] = np.nan
    return PoseSolution(r, T, converged & passed & finite, iterations, rel, pos_sigma, ang_sigma)


@dataclass
class IdealSignals:
    """Signals in ideal-dipole units (..., 3, 3), and per sample the model's relative residual at the pose
    the conversion used and whether it passed the gate (:func:`tracker_pose`)."""

    signal: np.ndarray
    residual: np.ndarray
    passed: np.ndarray
    #: per sample, how much more signal noise reaches the converted signal than the gains alone carry (1 for
    #: concentric coils; NaN where non-finite): :func:`noise_gain`
    noise_gain: np.ndarray


def noise_gain(tracker: Tracker, r: np.ndarray, T: np.ndarray) -> np.ndarray:
    """How much the conversion to ideal units amplifies signal noise at poses (r (F, 3) m, T (F, 3, 3)).

    The coil offsets' share ``D`` is taken at the pose the noisy signal gives, so to first order a
    noise ``n`` (3, 3) reaches the converted signal as ``C (n − ∂D δ)`` with ``δ = J⁺ n`` the pose
    error it causes (``J`` the model's pose Jacobian, ``∂D`` the share's) and ``C: n ↦ B⁻ᵀ n A⁻¹``
    the gains' map. Returns ``‖C (I − ∂D J⁺)‖_F / ‖C‖_F`` per pose: the rms error of the converted
    signal over the rms of the noise the gains alone carry, for independent equal noise on the nine
    entries. No estimate does better to first order: the pose (and so ``D``) is the least-squares
    one. It grows where the pose is weakly determined and ``D`` strong (near off-centre coils).
    """
    gains = Tracker(tracker.source_moments, tracker.sensor_moments, bias=tracker.bias)
    F = len(r)
    _, dS = tracker.pose_jacobian(r, T)
    _, dG = gains.pose_jacobian(r, T)
    J, dD = dS.reshape(F, 9, 6), (dS - dG).reshape(F, 9, 6)
    with np.errstate(all="ignore"):
        pinv = np.linalg.solve(np.swapaxes(J, 1, 2) @ J, np.swapaxes(J, 1, 2))  # (F, 6, 9)
    C = np.kron(np.linalg.inv(tracker.sensor_moments).T, np.linalg.inv(tracker.source_moments).T)  # row-major vec
    L = C @ (np.eye(9) - dD @ pinv)
    return np.linalg.norm(L, axis=(1, 2)) / np.linalg.norm(C)


def ideal_signals(S: ArrayLike, tracker: Tracker, hemisphere: str | ArrayLike | None = None, *,
                  noise_relative: float = 0.0) -> IdealSignals:
    """What the ideal tracker would read at the same pose (``--tracker-model``; docs/tracker.md).

    Concentric coils: the gain correction ``B⁻ᵀ (S − bias) A⁻¹``, exact for any field (the
    room's eddy currents are driven by the same source moments); every sample passes.
    With coil offsets, their share ``D(r, T) = S_model − (Bᵀ Tᵀ f_D(r) A + bias)`` is also
    removed, at the pose :func:`tracker_pose` solves (geometry-aware start, gate, retry;
    no output correction): exact in free space, second order in offset and distortion in
    a distorted room. There a sample's residual also holds what the room adds, so a sample
    that fails the gate is converted all the same and counted, not dropped.
    Non-finite matrices stay non-finite (and do not pass).
    """
    S = np.asarray(S, dtype=float)
    if S.shape[-2:] != (3, 3):
        raise InputError(f"signal matrices must have shape (..., 3, 3), got {S.shape}")
    lead = S.shape[:-2]
    flat = S.reshape(-1, 3, 3)
    finite = np.all(np.isfinite(flat.reshape(len(flat), 9)), axis=1)
    if tracker.is_ideal or tracker.is_concentric:
        out = flat.copy() if tracker.is_ideal else tracker.corrected(flat)
        return IdealSignals(out.reshape(S.shape), np.where(finite, 0.0, np.nan).reshape(lead), finite.reshape(lead),
                            np.where(finite, 1.0, np.nan).reshape(lead))
    h = hemisphere if hemisphere is None or isinstance(hemisphere, str) else np.broadcast_to(
        np.asarray(hemisphere, float), S.shape[:-1]).reshape(-1, 3)
    solution = tracker_pose(flat, tracker, h, correct=False, noise_relative=noise_relative)
    gains = Tracker(tracker.source_moments, tracker.sensor_moments, bias=tracker.bias)
    out = np.full(flat.shape, np.nan)
    ok = np.flatnonzero(finite)
    r, T = solution.position[ok], solution.rotation[ok]
    D = tracker.signal(r, T) - gains.signal(r, T)
    out[ok] = np.linalg.inv(tracker.sensor_moments).T @ (flat[ok] - tracker.bias - D) @ np.linalg.inv(
        tracker.source_moments)
    gain = np.full(len(flat), np.nan)
    gain[ok] = noise_gain(tracker, r, T)
    return IdealSignals(out.reshape(S.shape), solution.residual.reshape(lead),
                        (solution.converged & finite).reshape(lead), gain.reshape(lead))


def to_ideal(S: ArrayLike, tracker: Tracker, hemisphere: str | ArrayLike | None = None) -> np.ndarray:
    """Signals (..., 3, 3) in ideal-dipole units: what the ideal tracker would read at the same pose.

    The one place where a tracker model enters ivc's primary-field path: every later stage
    (fixtures, table, correction) then sees ``Tᵀ (f_D(r) + G)``, so the secondary field is
    what the room adds, not what the coils get wrong (:func:`ideal_signals`, which also says
    which samples passed the gate). ``hemisphere``: None for the side the calibration
    recorded (:attr:`Tracker.hemisphere`), else ``+x``. The output correction is not applied.
    """
    return ideal_signals(S, tracker, hemisphere).signal
