"""Calibration of the tracker's own model from signals at poses known up to constant transforms.

A precision rig (a motion stage, a robot, a grid board) knows each pose only through a
chain ``P = F_so · J_so · F_st · J_st · F_se`` (4x4, metres): ``J_so`` (the source's
known motion, e.g. a fixture rotation) and ``J_st`` (the stage's known motion) change
from point to point; ``F_so``, ``F_st``, ``F_se`` are constant transforms nobody
measured. :func:`calibrate` fits them together with the tracker's moment matrices and,
optionally, its coil offsets (:class:`ivc.dipole.tracker.Tracker`), by Levenberg-Marquardt
on all points at once with the analytic Jacobian. Each point's residual is weighted by
``1 / ‖S‖₂`` so that near and far points count alike; the residue of a point is
``‖S − S_pred‖_F / ‖S‖₂`` (docs/tracker.md).

Gauge: the model is unchanged by rotating or shifting the source frame, rotating or
shifting the sensor frame, or trading a scale between source and sensor. The fit fixes
these: ``A`` and ``B`` upper triangular (source coil x along source x, coil y in the xy
plane; the same for the sensor), ``B[2, 2] = 1``, and the coil centres' centroid at each
frame's origin. :func:`canonical_gauge` brings any model to that form.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from ivc import rotations
from ivc.dipole.field import field as dipole_field
from ivc.dipole.tracker import GATE_FACTOR, MIN_RESIDUAL_GATE, Tracker, model
from ivc.errors import TrackerError

__all__ = ["CalibrationResult", "Fixtures", "ParameterLayout", "calibrate", "calibration_jacobian", "canonical_gauge",
           "chain", "fit_output_correction", "model_gate", "pose_errors", "predicted_signal", "residue",
           "solve_chain_poses"]

_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def rigid_transform(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    X = np.eye(4)
    if R is not None:
        X[:3, :3] = R
    if t is not None:
        X[:3, 3] = t
    return X


def _inverse(X: np.ndarray) -> np.ndarray:
    R = np.swapaxes(X[..., :3, :3], -1, -2)
    out = np.zeros(X.shape)
    out[..., :3, :3] = R
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R, X[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


@dataclass
class Fixtures:
    """The constant transforms of the pose chain (4x4, metres): source, stage and sensor fixtures.

    ``motions`` and ``motion_errors`` (lists of 4x4, same length; empty by default): when
    the known source motions are only nominal (a fixture's 90-degree turns are not exact),
    the motion ``motions[k]`` is really ``motions[k] · motion_errors[k]``; the first is exact
    (the others are measured against it).
    """

    source: np.ndarray = field(default_factory=lambda: np.eye(4))
    stage: np.ndarray = field(default_factory=lambda: np.eye(4))
    sensor: np.ndarray = field(default_factory=lambda: np.eye(4))
    motions: list = field(default_factory=list)
    motion_errors: list = field(default_factory=list)

    def to_dict(self) -> dict:
        out = {"source": self.source.tolist(), "stage": self.stage.tolist(), "sensor": self.sensor.tolist()}
        if self.motions:
            out["source_motions"] = [np.asarray(m).tolist() for m in self.motions]
            out["source_motion_errors"] = [np.asarray(m).tolist() for m in self.motion_errors]
        return out

    @classmethod
    def from_dict(cls, data: dict) -> Fixtures:
        try:
            out = cls(*(np.array(data[k], dtype=float) for k in ("source", "stage", "sensor")),
                      [np.array(m, dtype=float) for m in data.get("source_motions", [])],
                      [np.array(m, dtype=float) for m in data.get("source_motion_errors", [])])
        except (KeyError, TypeError, ValueError) as error:
            raise TrackerError(f"malformed fixtures entry ({error})") from None
        if any(X.shape != (4, 4) for X in (out.source, out.stage, out.sensor, *out.motions, *out.motion_errors)):
            raise TrackerError("each fixture must be a 4x4 homogeneous transform")
        if len(out.motions) != len(out.motion_errors):
            raise TrackerError("source_motions and source_motion_errors must have the same length")
        return out

    def groups(self, J_so: np.ndarray) -> np.ndarray:
        """Index (N,) of each point's source motion in ``motions``."""
        group = np.full(len(J_so), -1)
        for k, m in enumerate(self.motions):
            group[np.all(np.isclose(J_so, m, atol=1e-9), axis=(1, 2))] = k
        if np.any(group < 0):
            raise TrackerError("a point's source motion is none of the calibration's: score only source "
                               "fixturings the tracker was calibrated with")
        return group

    def effective_source_motions(self, J_so: np.ndarray) -> np.ndarray:
        """``J_so`` (N, 4, 4) with each nominal motion's fitted error applied."""
        if not self.motions:
            return J_so
        return J_so @ np.asarray(self.motion_errors)[self.groups(J_so)]


def distinct_source_motions(J_so: np.ndarray) -> list[np.ndarray]:
    """The distinct source motions, the first point's first."""
    out: list[np.ndarray] = []
    for m in J_so:
        if not any(np.allclose(m, d, atol=1e-9) for d in out):
            out.append(m.copy())
    return out


def chain(fixtures: Fixtures, J_so: np.ndarray, J_st: np.ndarray) -> np.ndarray:
    """Sensor poses ``P = F_so J_so F_st J_st F_se`` (N, 4, 4) in the source frame, metres."""
    J_so = fixtures.effective_source_motions(np.broadcast_to(J_so, np.shape(J_st)))
    return fixtures.source @ J_so @ fixtures.stage @ J_st @ fixtures.sensor


def predicted_signal(tracker: Tracker, fixtures: Fixtures, J_so: np.ndarray, J_st: np.ndarray) -> np.ndarray:
    """The signal matrices (N, 3, 3) the model predicts at the chain's poses."""
    P = chain(fixtures, J_so, J_st)
    return model(P[:, :3, :3], P[:, :3, 3], tracker)[0]


def residue(S: np.ndarray, S_pred: np.ndarray) -> np.ndarray:
    """Per-point residue ``‖S − S_pred‖_F / ‖S‖₂`` (N,), dimensionless (the ILEMT authors' measure)."""
    return np.linalg.norm(S - S_pred, axis=(1, 2)) / np.linalg.norm(S, ord=2, axis=(1, 2))


def model_gate(tracker: Tracker, fixtures: Fixtures, S: np.ndarray, J_so: np.ndarray, J_st: np.ndarray) -> Tracker:
    """``tracker`` with the pose gate and hemisphere its calibration points give (docs/tracker.md).

    The gate is :data:`ivc.dipole.tracker.GATE_FACTOR` times the 99th percentile of the points'
    relative residuals ``‖S − S_pred‖_F / ‖S‖_F`` at the chain's poses (what the model leaves at
    a right pose, noise included; a solved pose leaves less), and at least
    :data:`ivc.dipole.tracker.MIN_RESIDUAL_GATE` (no real device's model is better). The hemisphere is the direction
    of the points' mean position in the source frame, when every point lies on its side.
    """
    P = chain(fixtures, J_so, J_st)
    pred = model(P[:, :3, :3], P[:, :3, 3], tracker)[0]
    relative = np.linalg.norm(S - pred, axis=(1, 2)) / np.linalg.norm(S, axis=(1, 2))
    gate = GATE_FACTOR * float(np.quantile(relative, 0.99))
    mean = P[:, :3, 3].mean(axis=0)
    side = mean / np.linalg.norm(mean)
    hemisphere = side if np.all(P[:, :3, 3] @ side > 0) else None
    return replace(tracker, residual_gate=max(gate, MIN_RESIDUAL_GATE), hemisphere=hemisphere)


def _qr_rotation(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``M = Q U``, Q a rotation (det +1), U upper triangular."""
    Q, U = np.linalg.qr(M)
    if np.linalg.det(Q) < 0:
        Q[:, 2] *= -1.0
        U[2, :] *= -1.0
    return Q, U


def canonical_gauge(tracker: Tracker, fixtures: Fixtures, J_so0: np.ndarray | None = None,
                    source_fixture_free: bool = True) -> tuple[Tracker, Fixtures]:
    """The same model (same predicted signals at every pose) in the fit's gauge (module docstring).

    A change of the source frame goes into ``F_so`` when ``source_fixture_free``, else into
    ``F_st`` through the (then constant) source motion ``J_so0`` (4, 4).
    """
    A, B = tracker.source_moments.copy(), tracker.sensor_moments.copy()
    p, q = tracker.source_offsets.copy(), tracker.sensor_offsets.copy()
    F_so, F_st, F_se = fixtures.source.copy(), fixtures.stage.copy(), fixtures.sensor.copy()
    J0 = np.eye(4) if J_so0 is None else J_so0

    errors = [np.asarray(e).copy() for e in fixtures.motion_errors]

    def change_source(X: np.ndarray) -> None:  # new source coordinates = X · old
        nonlocal F_so, F_st
        if source_fixture_free:
            F_so = X @ F_so
        else:
            base = F_so @ J0
            inner = _inverse(base) @ X @ base
            F_st = inner @ F_st
            for k, m in enumerate(fixtures.motions):  # keep every other source motion's points in place
                here = F_so @ m
                errors[k] = _inverse(here) @ X @ here @ errors[k] @ _inverse(inner)

    Q, A = _qr_rotation(A)
    p = p @ Q
    change_source(rigid_transform(Q.T))
    c = p.mean(axis=0)
    p = p - c
    change_source(rigid_transform(t=-c))
    Q, B = _qr_rotation(B)
    q = q @ Q
    F_se = F_se @ rigid_transform(Q)
    c = q.mean(axis=0)
    q = q - c
    F_se = F_se @ rigid_transform(t=c)
    s = B[2, 2]
    A, B = A * s, B / s
    clean = Tracker(A, B, p, q, dict(tracker.calibration), tracker.bias.copy())
    return clean, Fixtures(F_so, F_st, F_se, [np.asarray(m).copy() for m in fixtures.motions], errors)


@dataclass
class CalibrationResult:
    """A fitted tracker with its fixtures, and how well it fits the calibration points."""

    tracker: Tracker
    fixtures: Fixtures
    residue: np.ndarray  # (N,) per point, ‖S − S_pred‖_F / ‖S‖₂
    iterations: int
    converged: bool
    parameter_sigma: dict  # standard errors of the tracker's free parameters, same layout


class ParameterLayout:
    """Where each free parameter sits in θ, and how it moves the model."""

    def __init__(self, offsets: bool, source_fixture: bool, bias: bool = False, motion_groups: int = 0):
        self.offsets = offsets
        self.source_fixture = source_fixture
        self.bias = bias
        self.motion_groups = motion_groups
        n = 6 + 5
        self.off = n
        n += 12 if offsets else 0
        self.bias_at = n
        n += 9 if bias else 0
        self.fix = n
        n += 18 if source_fixture else 12
        self.motion_at = n
        n += 6 * max(motion_groups - 1, 0)
        self.size = n

    def apply(self, tracker: Tracker, fixtures: Fixtures, theta: np.ndarray) -> tuple[Tracker, Fixtures]:
        A, B = tracker.source_moments.copy(), tracker.sensor_moments.copy()
        p, q = tracker.source_offsets.copy(), tracker.sensor_offsets.copy()
        for k, (a, b) in enumerate(_UPPER):
            A[a, b] += theta[k]
        for k, (a, b) in enumerate(_UPPER[:5]):
            B[a, b] += theta[6 + k]
        if self.offsets:
            dp = theta[self.off : self.off + 6].reshape(2, 3)
            dq = theta[self.off + 6 : self.off + 12].reshape(2, 3)
            p += np.vstack([dp, -dp.sum(axis=0)])
            q += np.vstack([dq, -dq.sum(axis=0)])
        bias = tracker.bias.copy()
        if self.bias:
            bias += theta[self.bias_at : self.bias_at + 9].reshape(3, 3)
        steps = theta[self.fix : self.motion_at].reshape(-1, 6)

        def moved(X, eta):
            return X @ rigid_transform(rotations.to_matrix(rotations.from_rotvec(eta[:3])), eta[3:])

        F_se = moved(fixtures.sensor, steps[0])
        F_st = moved(fixtures.stage, steps[1])
        F_so = moved(fixtures.source, steps[2]) if self.source_fixture else fixtures.source
        errors = [np.asarray(e).copy() for e in fixtures.motion_errors]
        for k, eta in enumerate(theta[self.motion_at :].reshape(-1, 6), start=1):
            errors[k] = moved(errors[k], eta)
        return (Tracker(A, B, p, q, dict(tracker.calibration), bias),
                Fixtures(F_so, F_st, F_se, list(fixtures.motions), errors))

    def names(self) -> list[str]:
        out = [f"A[{a},{b}]" for a, b in _UPPER] + [f"B[{a},{b}]" for a, b in _UPPER[:5]]
        if self.offsets:
            out += [f"p[{i},{m}]" for i in range(2) for m in range(3)]
            out += [f"q[{i},{m}]" for i in range(2) for m in range(3)]
        if self.bias:
            out += [f"bias[{j},{i}]" for j in range(3) for i in range(3)]
        return out


def _adjoint_inverse(Y: np.ndarray) -> np.ndarray:
    """(N, 6, 6) map of a right increment η = (ω, v) of X in ``X · Y`` to the increment of the product."""
    R = np.swapaxes(Y[:, :3, :3], 1, 2)
    t = Y[:, :3, 3]
    skew = np.zeros((len(Y), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -t[:, 2], t[:, 1], -t[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = t[:, 2], -t[:, 1], t[:, 0]
    out = np.zeros((len(Y), 6, 6))
    out[:, :3, :3] = R
    out[:, 3:, 3:] = R
    out[:, 3:, :3] = -R @ skew
    return out


def calibration_jacobian(layout: ParameterLayout, tracker: Tracker, fixtures: Fixtures, J_so,
                         J_st) -> tuple[np.ndarray, np.ndarray]:
    """Predicted S (N, 3, 3) and ∂S/∂θ (N, 9, n)."""
    P = chain(fixtures, J_so, J_st)
    S, d = model(P[:, :3, :3], P[:, :3, 3], tracker, parts=True)
    N = len(S)
    J = np.zeros((N, 3, 3, layout.size))
    for k, (a, b) in enumerate(_UPPER):  # A[a, b]: source coil b
        J[:, :, b, k] = d.d_A[:, :, b, a]
    for k, (a, b) in enumerate(_UPPER[:5]):  # B[a, b]: sensor coil b
        J[:, b, :, 6 + k] = d.d_B[:, b, :, a]
    if layout.offsets:
        for i in range(2):
            for m in range(3):
                k = layout.off + 3 * i + m
                J[:, :, i, k] += d.d_p[:, :, i, m]
                J[:, :, 2, k] -= d.d_p[:, :, 2, m]
                k += 6
                J[:, i, :, k] += d.d_q[:, i, :, m]
                J[:, 2, :, k] -= d.d_q[:, 2, :, m]
    if layout.bias:
        J[..., layout.bias_at : layout.bias_at + 9] = np.eye(9).reshape(3, 3, 9)
    d_xi = np.concatenate([d.d_w, d.d_v], axis=-1)  # (N, 3, 3, 6): right increment of P
    k = layout.fix
    J[..., k : k + 6] = d_xi
    J_so = np.broadcast_to(J_so, J_st.shape)
    after_stage = J_st @ fixtures.sensor
    J[..., k + 6 : k + 12] = np.einsum("njia,nab->njib", d_xi, _adjoint_inverse(after_stage))
    if layout.motion_groups > 1:
        group = fixtures.groups(J_so)
        adjoint = _adjoint_inverse(fixtures.stage @ after_stage)
        for g in range(1, layout.motion_groups):
            rows = group == g
            at = layout.motion_at + 6 * (g - 1)
            J[rows, ..., at : at + 6] = np.einsum("njia,nab->njib", d_xi[rows], adjoint[rows])
    if layout.source_fixture:
        after_source = fixtures.effective_source_motions(J_so) @ fixtures.stage @ after_stage
        J[..., k + 12 : k + 18] = np.einsum("njia,nab->njib", d_xi, _adjoint_inverse(after_source))
    return S, J.reshape(N, 9, layout.size)


def _initial(S, J_so, J_st, source_fixture, stage_offsets, motions=()) -> tuple[Tracker, Fixtures]:
    """Start: nominally aligned fixtures with the stage ``d`` out along source x, y or z (the dipole
    model cannot tell +d from −d); A and B by alternating linear fits. The best start is kept."""
    best = None
    for d, axis in itertools.product(stage_offsets, (1, 0, 2)):
        fixtures = Fixtures(stage=rigid_transform(t=d * np.eye(3)[axis]), motions=list(motions),
                            motion_errors=[np.eye(4) for _ in motions])
        P = chain(fixtures, J_so, J_st)
        R, t = P[:, :3, :3], P[:, :3, 3]
        F = dipole_field(t)  # (N, 3, 3)
        B = np.eye(3)
        w = 1.0 / np.linalg.norm(S, ord=2, axis=(1, 2))
        for _ in range(6):
            # S = Bᵀ Rᵀ F A: linear in A given B, and in B given A
            L = np.swapaxes(R @ B, 1, 2)  # (N, 3, 3): S = L F A
            M = L @ F  # S[:, j, i] = Σ_l M[:, j, l] A[l, i]
            A = np.linalg.lstsq((M * w[:, None, None]).reshape(-1, 3),
                                (S * w[:, None, None]).reshape(-1, 3), rcond=None)[0]
            K = np.swapaxes(R, 1, 2) @ F @ A  # S = Bᵀ K  ->  Sᵀ = Kᵀ B
            Kt = np.swapaxes(K, 1, 2)
            B = np.linalg.lstsq((Kt * w[:, None, None]).reshape(-1, 3),
                                (np.swapaxes(S, 1, 2) * w[:, None, None]).reshape(-1, 3), rcond=None)[0]
        pred = np.swapaxes(B, 0, 1) @ np.swapaxes(R, 1, 2) @ F @ A
        cost = float(np.sum(residue(S, pred) ** 2))
        if np.all(np.isfinite([cost])) and (best is None or cost < best[0]):
            best = (cost, Tracker(A, B), fixtures)
    if best is None:
        raise TrackerError("no starting model fits the data: check the signals and the pose chain")
    return canonical_gauge(best[1], best[2], J_so[0], source_fixture)


def _levenberg_marquardt(layout, tracker, fixtures, S, J_so, J_st, weights, max_iterations, tolerance, progress):
    S_pred, J = calibration_jacobian(layout, tracker, fixtures, J_so, J_st)
    e = ((S - S_pred) * weights[:, None, None]).reshape(-1)
    Jw = -(J * weights[:, None, None]).reshape(-1, layout.size)
    cost = float(e @ e)
    damping = 1e-3
    converged = False
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        H = Jw.T @ Jw
        g = Jw.T @ e
        diag = np.maximum(np.diag(H), 1e-30 * np.diag(H).max())
        try:
            step = -np.linalg.solve(H + damping * np.diag(diag), g)
        except np.linalg.LinAlgError:
            damping *= 10.0
            continue
        t_trial, f_trial = layout.apply(tracker, fixtures, step)
        S_t, J_t = calibration_jacobian(layout, t_trial, f_trial, J_so, J_st)
        e_t = ((S - S_t) * weights[:, None, None]).reshape(-1)
        cost_t = float(e_t @ e_t)
        if progress is not None:
            progress(iterations, min(cost, cost_t))
        if cost_t <= cost:
            relative = (cost - cost_t) / max(cost, 1e-300)
            tracker, fixtures, e, cost = t_trial, f_trial, e_t, cost_t
            Jw = -(J_t * weights[:, None, None]).reshape(-1, layout.size)
            damping = max(damping * 0.3, 1e-12)
            if relative < tolerance:
                converged = True
                break
        else:
            damping *= 10.0
            if damping > 1e10:
                converged = True  # no step lowers the cost: at the numerical minimum
                break
    return tracker, fixtures, Jw, e, iterations, converged


def calibrate(
    S: np.ndarray,
    J_so: np.ndarray,
    J_st: np.ndarray,
    *,
    offsets: bool = True,
    bias: bool = False,
    output_correction: bool = True,
    fit_source_fixture: bool | None = None,
    source_motions: str = "exact",
    start: tuple[Tracker, Fixtures] | None = None,
    stage_offsets: tuple[float, ...] = (0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5),
    max_iterations: int = 200,
    tolerance: float = 1e-10,
    progress: Callable[[int, float], None] | None = None,
) -> CalibrationResult:
    """Fit a :class:`Tracker` and the chain's :class:`Fixtures` to signals at known-motion poses.

    Parameters
    ----------
    S : (N, 3, 3) measured signal matrices (row = sensor coil, column = source coil), any unit.
    J_so : (N, 4, 4) or (4, 4) known source motions; J_st : (N, 4, 4) known stage motions, metres.
    offsets : fit a position per coil (non-concentric coils); False: one centre each.
    fit_source_fixture : fit ``F_so``; by default only when the source motions differ
        (with one source motion ``F_so`` cannot be told from ``F_st``).
    source_motions : ``"exact"`` (default): the known source motions are exact; ``"free"``:
        each distinct source motion after the first is only nominal and gets its own fitted
        error transform (:attr:`Fixtures.motion_errors`; ``F_so`` is then redundant and not fitted).
    start : a starting model; by default nominally aligned fixtures, the stage at
        ``stage_offsets`` metres along source x, y or z (the best is kept), gains by linear fits.
    bias : also fit a constant added signal (electronic pick-up), :attr:`Tracker.bias`.
    output_correction : then solve the calibration points' poses with the fitted model and
        fit the tracker's output correction (affine in position, :meth:`Tracker.correct_pose`)
        that takes them to the chain's poses.
    progress : called as ``progress(iteration, cost)``.

    The concentric model is fitted first; with ``offsets`` the coil offsets are then added.
    """
    S = np.asarray(S, dtype=float)
    J_st = np.asarray(J_st, dtype=float)
    J_so = np.broadcast_to(np.asarray(J_so, dtype=float), J_st.shape)
    if S.ndim != 3 or S.shape[1:] != (3, 3) or J_st.shape != (len(S), 4, 4):
        raise TrackerError(f"need S (N, 3, 3) and J_st (N, 4, 4) for the same N; got {S.shape} and {J_st.shape}")
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(J_st)) and np.all(np.isfinite(J_so))):
        raise TrackerError("signals and pose-chain transforms must be finite; drop the bad points first")
    if len(S) < 12:
        raise TrackerError(f"{len(S)} points cannot fix a tracker model and its fixtures; record at least 12")
    if source_motions not in ("exact", "free"):
        raise TrackerError(f"source_motions must be 'exact' or 'free', got {source_motions!r}")
    distinct = distinct_source_motions(J_so)
    motions = distinct if source_motions == "free" and len(distinct) > 1 else []
    if motions:
        fit_source_fixture = False
    elif fit_source_fixture is None:
        fit_source_fixture = len(distinct) > 1
    weights = 1.0 / np.linalg.norm(S, ord=2, axis=(1, 2))
    if start is None:
        tracker, fixtures = _initial(S, J_so, J_st, fit_source_fixture, stage_offsets, motions)
    else:
        start_fixtures = start[1]
        if motions and not start_fixtures.motions:
            start_fixtures = Fixtures(start_fixtures.source, start_fixtures.stage, start_fixtures.sensor, motions,
                                      [np.eye(4) for _ in motions])
        tracker, fixtures = canonical_gauge(start[0], start_fixtures, J_so[0], fit_source_fixture)
    total = 0
    layouts = [ParameterLayout(False, fit_source_fixture, motion_groups=len(motions))]
    if offsets or bias:
        layouts.append(ParameterLayout(offsets, fit_source_fixture, bias, motion_groups=len(motions)))
    for layout in layouts:
        tracker, fixtures, Jw, e, its, converged = _levenberg_marquardt(
            layout, tracker, fixtures, S, J_so, J_st, weights, max_iterations, tolerance, progress)
        total += its
    dof = max(len(e) - layout.size, 1)
    sigma2 = float(e @ e) / dof
    covariance = np.linalg.pinv(Jw.T @ Jw) * sigma2
    std = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    parameter_sigma = dict(zip(layout.names(), std[: layout.fix].tolist(), strict=True))
    tracker = model_gate(tracker, fixtures, S, J_so, J_st)
    if output_correction:
        tracker = fit_output_correction(tracker, fixtures, S, J_so, J_st)
    pred = predicted_signal(tracker, fixtures, J_so, J_st)
    return CalibrationResult(tracker, fixtures, residue(S, pred), total, converged, parameter_sigma)


def solve_chain_poses(tracker: Tracker, fixtures: Fixtures, S: np.ndarray, J_so: np.ndarray, J_st: np.ndarray,
                      correct: bool = True):
    """Solve each point's pose with ``tracker``; also return the chain's poses.

    The hemisphere is the one the tracker's calibration recorded (:attr:`Tracker.hemisphere`),
    else each point's own side from the chain. Nothing else of the chain enters the solve.
    """
    from ivc.pose.tracker import tracker_pose

    P = chain(fixtures, J_so, J_st)
    side = tracker.hemisphere if tracker.hemisphere is not None else P[:, :3, 3]
    return tracker_pose(S, tracker, side, correct=correct), P


def pose_errors(tracker: Tracker, fixtures: Fixtures, S: np.ndarray, J_so: np.ndarray, J_st: np.ndarray,
                correct: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and orientation (rad) errors (N,) of the solved poses against the chain's poses."""
    solution, P = solve_chain_poses(tracker, fixtures, S, J_so, J_st, correct)
    position = np.linalg.norm(solution.position - P[:, :3, 3], axis=1)
    angle = rotations.angle_between_matrices(solution.rotation, P[:, :3, :3])
    return position, angle


def fit_output_correction(tracker: Tracker, fixtures: Fixtures, S: np.ndarray, J_so: np.ndarray,
                          J_st: np.ndarray, solution=None) -> Tracker:
    """``tracker`` with the affine output correction that best takes its solved poses to the chain's.

    Least squares over the points whose pose passed the gate (``converged``; a wrong minimum
    never enters): ``r_chain − r ≈ W_p [r; 1]`` and ``log(T_chain Tᵀ) ≈ W_r [r; 1]`` (rotation
    vectors, source frame). ``solution``: the points' poses solved without correction
    (:class:`ivc.pose.solver.PoseSolution`), if the caller has them.
    """
    plain = replace(tracker, position_correction=np.zeros((3, 4)), rotation_correction=np.zeros((3, 4)))
    P = chain(fixtures, J_so, J_st)
    if solution is None:
        solution, _ = solve_chain_poses(plain, fixtures, S, J_so, J_st, correct=False)
    ok = solution.converged & np.all(np.isfinite(solution.position), axis=1)
    if ok.sum() < 12:
        raise TrackerError(f"only {int(ok.sum())} calibration poses passed the gate; cannot fit an output "
                           "correction (calibrate with output_correction=False, or check the recordings)")
    r = solution.position[ok]
    h = np.concatenate([r, np.ones((len(r), 1))], axis=1)
    W_p = np.linalg.lstsq(h, P[ok, :3, 3] - r, rcond=None)[0].T
    dw = rotations.to_rotvec(rotations.from_matrix(P[ok, :3, :3] @ np.swapaxes(solution.rotation[ok], 1, 2)))
    W_r = np.linalg.lstsq(h, dw, rcond=None)[0].T
    return replace(plain, calibration=dict(tracker.calibration), position_correction=W_p, rotation_correction=W_r)
