"""Self-calibration of a pose-only map: the room's field and the wand's poses fitted together.

A pose-only session knows the true pose of the wand only through sensor 0, traced back through the cube's field,
and that field comes from the survey's 8 vertex poses (:mod:`ivc.fixtures.reported_mapping`). Where the room's
secondary field rivals the source's, 8 poses do not pin a field that bends across the cube, sensor 0 inherits the
cube field's error (a millimetre on the strong scene), and so does every pair the room's fit uses.

The wand itself says more: its sensors are one rigid body, so in every frame all of them, sensor 0 included,
must be reported as the tracker model of one field reports a rigid body at one pose. Here the field's coefficients
``c`` (the harmonic expansion of :mod:`ivc.pose.reported_fit`) and every frame's wand pose ``(p_f, R_f)`` (sensor 0's
position and rotation) are fitted together, a bundle adjustment, to the six pose residuals of every (frame, sensor)

    e = [v − φ(r),  L · rotvec(Q Tᵀ C(r)ᵀ)],   r = p_f + R_f a_i,  T = R_f B_i

(``a_i``, ``B_i``: the wand calibration), plus the survey's vertex pairs, whose true poses are known and which
fix the frame the rigid motions of everything would otherwise leave free. Levenberg-Marquardt steps solve the
normal equations by the Schur complement: each frame's 6 x 6 block is eliminated, leaving a system in ``c`` alone.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg.blas import dsyrk

from ivc import rotations
from ivc.fixtures.reported_mapping import PoseFixtureModel, PoseSweepMapping
from ivc.lut.refine import skew
from ivc.pose.precision import reported_noise
from ivc.pose.reported_fit import ORIENTATION_LENGTH, ROW_WEIGHT, Basis, PosePairs, design, pose_residuals, predicted
from ivc.pose.tracker_solver import distortion
from ivc.session import Session
from ivc.truth import percentiles

#: Levenberg-Marquardt iterations at most, and the relative drop of the cost they stop below
ITERATIONS, RELATIVE_TOLERANCE = 20, 1e-4
INITIAL_DAMPING = 1e-4
#: Gauss-Newton steps of each frame's pose in a fixed field
FRAME_ITERATIONS = 2
#: frames the adjustment fits at most (every k-th of the traced ones): enough to pin the field, few enough to be quick
FRAMES = 3000
#: frames per pass's chunk (their Jacobians in the coefficients are held at once)
CHUNK_FRAMES = 500
#: the step (m) of the central differences of the secondary field in position
STEP = 1e-5


@dataclass
class WandFrames:
    """The wand's sweep for the adjustment: per frame sensor 0's pose ``position`` (F, 3) m, ``rotation`` (F, 3, 3)
    (the unknowns, in the declared frame), what each sensor reported, ``reported_position`` (F, W, 3) m and
    ``reported_rotation`` (F, W, 3, 3), which samples count, ``use`` (F, W), and each sample's weight (F, W) (its
    residual's multiplier: the inverse of its reported pose's noise, relative; None: all 1)."""

    position: np.ndarray
    rotation: np.ndarray
    reported_position: np.ndarray
    reported_rotation: np.ndarray
    use: np.ndarray
    weight: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.position)

    def subset(self, frames) -> WandFrames:
        return WandFrames(self.position[frames], self.rotation[frames], self.reported_position[frames],
                          self.reported_rotation[frames], self.use[frames],
                          None if self.weight is None else self.weight[frames])

    def moved(self, step: np.ndarray) -> WandFrames:
        """The frames with their poses moved by ``step`` (F, 6): ``p += δp``, ``R ← exp([δθ]×) R``."""
        turn = rotations.to_matrix(rotations.from_rotvec(step[:, 3:]))
        return WandFrames(self.position + step[:, :3], turn @ self.rotation, self.reported_position,
                          self.reported_rotation, self.use, self.weight)


def _field(basis: Basis, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    return np.swapaxes(basis(r), 1, 2) @ c


def sample_terms(frames: WandFrames, levers: np.ndarray, turns: np.ndarray, basis: Basis, c: np.ndarray, solver: str,
                 hemisphere: str, jacobians: bool = True, coefficients: bool = True):
    """Residuals of the used samples of ``frames`` (n, 6) (metres; orientation as metres via L), which frame each is
    (n,), and with ``jacobians`` their derivatives in the coefficients (n, 6, c.size) and in the frame's pose
    increment ``(δp, δθ)`` (n, 6, 6), ``R ← exp([δθ]×) R`` (without ``coefficients``, the latter only); all of them
    times the samples' weights. ``levers`` (W, 3), ``turns`` (W, 3, 3): the wand calibration's ``a_i`` and ``B_i``."""
    f, i = np.nonzero(frames.use)
    arm = np.einsum("nij,nj->ni", frames.rotation[f], levers[i])
    r = frames.position[f] + arm
    T = frames.rotation[f] @ turns[i]
    observed = PosePairs(r, T, frames.reported_position[f, i], frames.reported_rotation[f, i], f, i)
    w = np.ones(len(f)) if frames.weight is None else frames.weight[f, i]
    if not jacobians:
        position, turn = distortion(r, _field(basis, c, r), solver=solver, hemisphere=hemisphere)
        return w[:, None] * pose_residuals(observed, position, turn), f
    b = basis(r)
    G = np.swapaxes(b, 1, 2) @ c
    dG = np.stack([(_field(basis, c, r + STEP * e) - _field(basis, c, r - STEP * e)) / (2 * STEP)
                   for e in np.eye(3)], axis=-1)
    position, turn, dphi, domega, J = distortion(r, G, dG, solver, hemisphere, jacobian=True)
    e = w[:, None] * pose_residuals(observed, position, turn)
    D = -w[:, None, None] * np.concatenate([dphi, ORIENTATION_LENGTH * domega], axis=1)  # ∂e/∂r (n, 6, 3)
    Xp = np.concatenate([D, -D @ skew(arm)], axis=2)
    Xp[:, 3:, 3:] -= (w * ORIENTATION_LENGTH)[:, None, None] * turn
    if not coefficients:
        return e, f, Xp
    return e, f, -design(J, b) * ROW_WEIGHT[None, :, None] * w[:, None, None], Xp


@dataclass
class _Pass:
    cost: float
    schur: np.ndarray  # (P, P) the reduced normal matrix Σ Xcᵀ Xc − Σ_f Hcf Hff⁻¹ Hfc, before damping
    rhs: np.ndarray  # (P,)
    Hff: np.ndarray  # (F, 6, 6)
    Hfc: np.ndarray  # (F, 6, P)
    gf: np.ndarray  # (F, 6)
    Hcc_diag: np.ndarray  # (P,)


def _cost(frames, levers, turns, basis, c, anchors, anchor_weight, solver, hemisphere) -> float:
    total = 0.0
    for start in range(0, len(frames), CHUNK_FRAMES):
        e, _ = sample_terms(frames.subset(slice(start, start + CHUNK_FRAMES)), levers, turns, basis, c, solver,
                            hemisphere, jacobians=False)
        total += float(np.sum(e**2))
    position, turn, _, _ = predicted(anchors.position, basis, c, solver, hemisphere)
    return total + float(np.sum((anchor_weight[:, None] * pose_residuals(anchors, position, turn)) ** 2))


def _normal(frames, levers, turns, basis, c, anchors, anchor_weight, solver, hemisphere) -> _Pass:
    P, F = c.size, len(frames)
    Hcc, gc = np.zeros((P, P)), np.zeros(P)
    Hff, Hfc, gf = np.zeros((F, 6, 6)), np.zeros((F, 6, P)), np.zeros((F, 6))
    cost = 0.0
    for start in range(0, F, CHUNK_FRAMES):
        part = slice(start, min(start + CHUNK_FRAMES, F))
        e, f, Xc, Xp = sample_terms(frames.subset(part), levers, turns, basis, c, solver, hemisphere)
        f = f + start
        cost += float(np.sum(e**2))
        flat = Xc.reshape(-1, P)
        Hcc += dsyrk(1.0, flat.T, trans=0)
        gc += flat.T @ e.reshape(-1)
        np.add.at(Hff, f, np.swapaxes(Xp, 1, 2) @ Xp)
        np.add.at(Hfc, f, np.swapaxes(Xp, 1, 2) @ Xc)
        np.add.at(gf, f, np.einsum("nai,na->ni", Xp, e))
    Hcc += np.triu(Hcc, 1).T
    position, turn, J, b = predicted(anchors.position, basis, c, solver, hemisphere)
    ea = anchor_weight[:, None] * pose_residuals(anchors, position, turn)
    Xa = (-design(J, b) * ROW_WEIGHT[None, :, None] * anchor_weight[:, None, None]).reshape(-1, P)
    Hcc += Xa.T @ Xa
    gc += Xa.T @ ea.reshape(-1)
    cost += float(np.sum(ea**2))
    return _Pass(cost, Hcc, gc, Hff, Hfc, gf, np.diag(Hcc).copy())


def _step(normal: _Pass, damping: float) -> tuple[np.ndarray, np.ndarray]:
    """The damped Gauss-Newton step ``(δc (P,), δpose (F, 6))`` minimising ``|e + Xc δc + Xp δpose|²``."""
    diagonal = np.einsum("fii->fi", normal.Hff)
    ridge = 1e-12 * np.maximum(diagonal.sum(axis=1), 1e-300)  # keeps a frame that barely sees a direction solvable
    Hff = normal.Hff + (damping * diagonal + ridge[:, None])[..., None] * np.eye(6)
    L = np.linalg.cholesky(Hff)
    W = np.linalg.solve(L, normal.Hfc)  # L⁻¹ Hfc (F, 6, P)
    w = np.linalg.solve(L, normal.gf[..., None])[..., 0]
    flat = W.reshape(-1, W.shape[-1])
    S = normal.schur - (dsyrk(1.0, flat.T, trans=0))
    S = np.triu(S) + np.triu(S, 1).T
    S += np.diag(damping * normal.Hcc_diag)
    rhs = -(normal.rhs - flat.T @ w.reshape(-1))
    scale = np.sqrt(np.maximum(np.diag(S), 1e-300))
    dc = np.linalg.solve(S / np.outer(scale, scale) + 1e-12 * np.eye(len(S)), rhs / scale) / scale
    # δpose = Hff⁻¹ (−g_f − Hfc δc) = L⁻ᵀ (−w − W δc)
    dp = np.linalg.solve(np.swapaxes(L, 1, 2), (-w - W @ dc)[..., None])[..., 0]
    return dc, dp


def adjust(frames: WandFrames, levers: np.ndarray, turns: np.ndarray, basis: Basis, coefficients: np.ndarray,
           anchors: PosePairs, anchor_weight: np.ndarray, solver: str = "closed-form", hemisphere: str = "+x",
           iterations: int = ITERATIONS, progress: Callable[[str], None] | None = None
           ) -> tuple[np.ndarray, WandFrames, dict]:
    """Fit the coefficients (K, 3) and the frames' poses together (the module docstring). ``anchors``: pairs whose
    true poses are known (the survey's vertices), each weighted by ``anchor_weight`` (n,) (about the square root of
    the frames it averages). Returns the coefficients, the frames at their fitted poses, and a report."""
    c = np.asarray(coefficients, float).copy()
    damping = INITIAL_DAMPING
    normal = _normal(frames, levers, turns, basis, c, anchors, anchor_weight, solver, hemisphere)
    history = [normal.cost]
    for _ in range(iterations):
        while True:
            dc, dp = _step(normal, damping)
            trial_c, trial_frames = c + dc.reshape(c.shape), frames.moved(dp)
            cost = _cost(trial_frames, levers, turns, basis, trial_c, anchors, anchor_weight, solver, hemisphere)
            if np.isfinite(cost) and cost < normal.cost:
                damping = max(damping * 0.3, 1e-9)
                break
            damping *= 10.0
            if damping > 1e6:
                break
        if not (np.isfinite(cost) and cost < normal.cost):
            break
        drop = normal.cost - cost
        c, frames = trial_c, trial_frames
        normal = _normal(frames, levers, turns, basis, c, anchors, anchor_weight, solver, hemisphere)
        history.append(normal.cost)
        if progress is not None:
            progress(f"cost {normal.cost:.6g}, damping {damping:.1e}")
        if drop < RELATIVE_TOLERANCE * cost:
            break
    n = int(frames.use.sum()) + len(anchors)
    return c, frames, {"rms_mm_by_iteration": [1000 * float(np.sqrt(h / n)) for h in history]}


def _frame_costs(frames: WandFrames, levers, turns, basis, c, solver, hemisphere, jacobians: bool = True):
    """Each frame's sum of squared (weighted) residuals (F,), and the samples' terms for its Gauss-Newton step
    (residuals, frames, and with ``jacobians`` the pose Jacobians; else None)."""
    terms = sample_terms(frames, levers, turns, basis, c, solver, hemisphere, jacobians, coefficients=False)
    e, f = terms[0], terms[1]
    return np.bincount(f, np.sum(e**2, axis=1), minlength=len(frames)), e, f, terms[2] if jacobians else None


def solve_frames(frames: WandFrames, levers: np.ndarray, turns: np.ndarray, basis: Basis, c: np.ndarray,
                 solver: str = "closed-form", hemisphere: str = "+x", iterations: int = FRAME_ITERATIONS
                 ) -> tuple[WandFrames, np.ndarray]:
    """Every frame's wand pose in the field of coefficients ``c`` held fixed: Gauss-Newton on each frame's six
    unknowns, a step kept per frame where it lowers that frame's residual. Returns the frames at their poses and
    each frame's RMS (weighted) pose residual (F,) (m)."""
    parts, rms = [], []
    for start in range(0, len(frames), CHUNK_FRAMES):
        part = frames.subset(slice(start, start + CHUNK_FRAMES))
        cost, e, f, Xp = _frame_costs(part, levers, turns, basis, c, solver, hemisphere)
        for k in range(iterations):
            H, g = np.zeros((len(part), 6, 6)), np.zeros((len(part), 6))
            np.add.at(H, f, np.swapaxes(Xp, 1, 2) @ Xp)
            np.add.at(g, f, np.einsum("nai,na->ni", Xp, e))
            ridge = 1e-12 * np.maximum(np.einsum("fii->f", H), 1e-30)[:, None, None] * np.eye(6)
            trial = part.moved(-np.linalg.solve(H + ridge, g[..., None])[..., 0])
            last = k == iterations - 1  # the last step's Jacobians are never used
            new, e_new, _, Xp_new = _frame_costs(trial, levers, turns, basis, c, solver, hemisphere, not last)
            better = new < cost
            part = replace(part, position=np.where(better[:, None], trial.position, part.position),
                           rotation=np.where(better[:, None, None], trial.rotation, part.rotation))
            cost = np.where(better, new, cost)
            if last or not better.any():
                break
            took = better[f]  # the samples of the frames whose step was kept take their new terms
            e, Xp = np.where(took[:, None], e_new, e), np.where(took[:, None, None], Xp_new, Xp)
        parts.append(part)
        rms.append(np.sqrt(cost / np.maximum(np.bincount(f, minlength=len(part)), 1)))
    out = WandFrames(*(np.concatenate([getattr(p, k) for p in parts]) for k in ("position", "rotation",
                                                                                 "reported_position",
                                                                                 "reported_rotation", "use")),
                     frames.weight)
    return out, np.concatenate(rms)


def self_calibrate(session: Session, model: PoseFixtureModel, mapping: PoseSweepMapping, basis: Basis,
                   coefficients: np.ndarray, solver: str = "closed-form", frames: int = FRAMES,
                   progress: Callable[[str], None] | None = None) -> tuple[PoseSweepMapping, np.ndarray, dict]:
    """The sweep's wand poses and the room's field fitted together (:func:`adjust`) on every k-th of the frames
    whose sensor 0 was traced (at most ``frames``), starting from ``coefficients`` (K, 3) of ``basis``; then every
    traced frame's wand pose solved in that field (:func:`solve_frames`). Returns ``mapping`` with the wand's poses
    and the pairs (sensor 0's included: its pose no longer comes from the cube's field alone) redone, the adjusted
    coefficients, and a report (sensor 0's move, the residuals before and after)."""
    sweep = session.steps["wand_sweep"]
    keep = mapping.keep
    traced = np.flatnonzero(keep[:, 0])
    with np.errstate(invalid="ignore"):
        Q = rotations.to_matrix(np.where(keep[..., None], sweep.quaternion, [1.0, 0.0, 0.0, 0.0]))
    reported = np.where(keep[traced, :, None], sweep.position[traced], 0.0)
    # each sample weighted by the inverse of its reported pose's noise (the free-space bound, relative): the far
    # sensors' poses are several times noisier than the near ones', and would otherwise pull the wand as hard
    noise = np.where(keep[traced], reported_noise(reported, Q[traced], 1.0).reshape(keep[traced].shape), np.nan)
    unit = float(np.nanmedian(noise))
    weight = np.where(keep[traced], unit / np.where(keep[traced], noise, 1.0), 0.0)
    everything = WandFrames(mapping.positions[traced, 0], mapping.rotations[traced, 0], reported, Q[traced],
                            keep[traced], weight)
    levers, turns = model.wand.positions, model.wand.rotations
    h = session.hemisphere
    stride = max(1, -(-len(traced) // frames))
    averaged = np.maximum(session.steps["cube_survey"].valid_mask.sum(axis=0), 1).astype(float)
    anchor_weight = np.sqrt(averaged) * unit / reported_noise(model.pairs.reported_position,
                                                              model.pairs.reported_rotation, 1.0)
    subset = everything.subset(slice(None, None, stride))
    c, adjusted, report = adjust(subset, levers, turns, basis, coefficients, model.pairs, anchor_weight, solver, h,
                                 progress=progress)
    # every frame starts moved as the adjusted frame nearest in time moved: sensor 0's traced error is the cube
    # field's, smooth along the sweep, so the frames start close and two steps solve them
    nearest = np.minimum(np.rint(np.arange(len(everything)) / stride).astype(np.int64), len(subset) - 1)
    turn = adjusted.rotation @ np.swapaxes(subset.rotation, 1, 2)
    start = replace(everything, position=everything.position + (adjusted.position - subset.position)[nearest],
                    rotation=turn[nearest] @ everything.rotation)
    solved, rms = solve_frames(start, levers, turns, basis, c, solver, h)
    positions, rots = mapping.positions.copy(), mapping.rotations.copy()
    positions[traced], rots[traced] = model.wand.propagate(solved.position, solved.rotation)
    frame, sensor = np.nonzero(keep)
    pairs = PosePairs(positions[frame, sensor], rots[frame, sensor], sweep.position[frame, sensor],
                      Q[frame, sensor], frame, sensor)
    moved = np.linalg.norm(solved.position - everything.position, axis=1)
    report.update(frames=int(len(traced[::stride])), stride=stride, survey_weight=float(np.median(anchor_weight)),
                  sensor0_moved_mm=percentiles(moved, 1000), frame_rms_mm=percentiles(rms, 1000))
    return replace(mapping, positions=positions, rotations=rots, pairs=pairs), c, report
