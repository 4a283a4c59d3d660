"""Corrected poses from measured signals and a look-up table (docs/math.md §9), batched or streaming.

Every result carries per-sample flags; a pose is never returned without them:

``OUTSIDE``        the corrected position is outside the mapped volume (the table says nothing there)
``NOT_CONVERGED``  the solve did not converge
``HIGH_RESIDUAL``  the model explains the signal poorly: rms(M − T S)/rms(S) above the limit, by default a
                   multiple of what the tracker's noise and the table's cross-validated model error explain
                   at that pose (:mod:`ivc.correct.residual_gate`)
``INVALID_INPUT``  the signal (or reported pose) is not finite or is all zeros, or the sample was marked invalid
``LOW_PRECISION``  the pose's predicted precision is worse than the limit (default 0.8 mm RMS where the
                   tracker's noise is known: :mod:`ivc.correct.precision`)

Flags combine bitwise; 0 means the pose is trusted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ivc import compiled, dipole, rotations
from ivc.correct import kernels as _kernels
from ivc.correct.flags import HIGH_RESIDUAL, INVALID_INPUT, LOW_PRECISION, NOT_CONVERGED, OUTSIDE
from ivc.correct.precision import DEFAULT, PrecisionGate, residual_widening
from ivc.correct.residual_gate import MAX_RESIDUAL, ResidualGate
from ivc.dipole.pose import hemisphere_vector
from ivc.errors import InputError
from ivc.table.grid import GridField
from ivc.table.lookup import LookupTable

FLAG_NAMES = {OUTSIDE: "outside the mapped volume", NOT_CONVERGED: "not converged",
              HIGH_RESIDUAL: "residual too high", INVALID_INPUT: "invalid input",
              LOW_PRECISION: "predicted precision over the limit"}
MAX_ITERATIONS = 50
STEP_TOLERANCE = 1e-7  # m: a tenth of a micrometre
#: batches of at least this many frames start cold frames from the table's correction map
#: (``ivc.correct.seed_map``, built once per corrector: about as long as correcting a few thousand frames)
SEED_MAP_FRAMES = 4096


def describe(flags: int) -> str:
    """Plain words for a flag value."""
    return ", ".join(name for bit, name in FLAG_NAMES.items() if flags & bit) or "ok"


@dataclass
class Correction:
    """Corrected poses (..., 3) m and (..., 4) [w, x, y, z], with ``flags`` (...) uint8, the relative
    ``residual`` and the solver's ``iterations``. Non-finite input gives NaN poses flagged INVALID_INPUT.
    ``precision`` (...) m and ``orientation_precision`` (...) rad: each pose's predicted RMS error from the
    tracker's signal noise (``ivc.pose.precision``; a signal's pose widened where its residual exceeds the noise,
    ``ivc.correct.precision.residual_widening``; a reported pose's with the table's own error; NaN where there is
    no pose), when the corrector was asked for them, else None."""

    position: np.ndarray
    quaternion: np.ndarray
    flags: np.ndarray
    residual: np.ndarray
    iterations: np.ndarray
    precision: np.ndarray | None = None
    orientation_precision: np.ndarray | None = None

    @property
    def ok(self) -> np.ndarray:
        return self.flags == 0

    def assign(self, index, other: Correction, rows=slice(None)) -> None:
        """Write ``other``'s samples ``rows`` into this correction's samples ``index`` (every array this one holds)."""
        for key in ("position", "quaternion", "flags", "residual", "iterations", "precision", "orientation_precision"):
            target = getattr(self, key)
            if target is not None:
                target[index] = getattr(other, key)[rows]


#: the correction-map argument of a kernel run without one (never read: ``use_map`` is False)
_NO_MAP = (np.zeros((4, 4, 4, 3)), np.zeros((1, 1, 1), dtype=bool), np.zeros(3), 1.0, np.array([2, 2, 2]), True)


class Corrector:
    """Applies a table to measurements: :meth:`batch` for arrays of frames, :meth:`update` for a live stream.

    ``interpolation``: ``cubic`` (default) or ``linear``. ``hemisphere``: where the sensors are
    (default: the table's). ``max_residual``: one HIGH_RESIDUAL limit of rms(M − T S)/rms(S) for every pose;
    default None: each pose's limit is :data:`~ivc.correct.residual_gate.RESIDUAL_SIGMAS` times the residual the
    signal noise and the table's cross-validated model error explain there (:class:`ResidualGate`; the fixed
    :data:`MAX_RESIDUAL` for a table that records neither, :attr:`residual_gate` says which). ``seed_map``: whether cold
    frames of batches of at least :data:`SEED_MAP_FRAMES` start from the table's correction map
    (``ivc.correct.seed_map``; False: always from the fixed point, as smaller batches do).

    Predicted precision (docs/trust.md): every pose carries its predicted RMS position and orientation
    error, the Cramér-Rao bound of a single frame from the table's field and the tracker's white signal
    noise ``signal_noise`` (signal units; default: the noise the table's fit measured on the session's
    static steps), widened where the pose's own residual says the table is off there by more than the noise
    (:func:`~ivc.correct.precision.residual_widening`), and poses predicted less precise than ``max_precision``
    (m; default :data:`ivc.correct.precision.MAX_PRECISION`; None: no gate) are flagged LOW_PRECISION. Where the
    noise is unknown nothing is predicted and :attr:`gate` says so; ``precision=False`` predicts nothing.
    """

    def __init__(self, table: LookupTable | GridField, hemisphere: str | None = None, interpolation: str = "cubic",
                 max_residual: float | None = None, max_iterations: int = MAX_ITERATIONS, seed_map: bool = True,
                 precision: bool = True, max_precision: float | str | None = DEFAULT,
                 signal_noise: float | None = None):
        self.field = table.field(interpolation) if isinstance(table, LookupTable) else table
        hemisphere = hemisphere or (table.hemisphere if isinstance(table, LookupTable) else "+x")
        self.hemisphere = hemisphere
        self._h = hemisphere_vector(hemisphere)
        self.residual_gate = ResidualGate.resolve(table, max_residual, signal_noise)
        #: the solver retries other starts above this residual (the fixed limit; today's where the gate scales)
        self.max_residual = self.residual_gate.fixed or MAX_RESIDUAL
        self.max_iterations = int(max_iterations)
        self._previous: dict = {}
        self._seed_map = None
        self.use_seed_map = bool(seed_map)
        self.gate = PrecisionGate.resolve(table, precision, max_precision, signal_noise)

    @property
    def signal_noise(self) -> float | None:
        """The white noise per signal entry the precision is predicted from (None: not predicted)."""
        return self.gate.sigma

    @property
    def max_precision(self) -> float | None:
        """The LOW_PRECISION limit (m; None: no gate)."""
        return self.gate.limit

    def predict_precision(self, position: np.ndarray, quaternion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predicted RMS position error (N,) m and orientation error (N,) rad of single-frame poses at
        ``position`` (N, 3) m, ``quaternion`` (N, 4), from the table's field and :attr:`signal_noise`
        (``ivc.pose.precision``); NaN where the pose is not finite. The noise's share only: a corrected pose's
        precision is also widened by its residual (:meth:`batch`), which a pose without its signal does not have."""
        if self.signal_noise is None:
            raise InputError(f"this corrector predicts no precision ({self.gate.note})")
        position = np.ascontiguousarray(np.asarray(position, float).reshape(-1, 3))
        quaternion = np.asarray(quaternion, float).reshape(-1, 4)
        if len(position) != len(quaternion):
            raise InputError(f"{len(position)} positions but {len(quaternion)} orientations")
        with np.errstate(invalid="ignore"):
            T = np.ascontiguousarray(rotations.to_matrix(quaternion))
        return self._precision(position, T)

    def _precision(self, r: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = len(r)
        out_r, out_a = np.empty(n), np.empty(n)
        bad = ~(np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(T.reshape(n, 9)), axis=1))
        kernel = compiled.choose(_kernels.precision_serial if n < 64 else _kernels.precision_kernel, n)
        kernel(np.ascontiguousarray(np.where(bad[:, None], np.nan, r)),
               np.ascontiguousarray(np.where(bad[:, None, None], np.eye(3), T)), self.field.kernel_grid,
               float(self.signal_noise), out_r, out_a)
        return out_r, out_a

    def seed_map(self) -> GridField:
        """The correction map cold frames of a large batch start from (``ivc.correct.seed_map``), built on
        first use and kept."""
        if self._seed_map is None:
            from ivc.correct.seed_map import correction_seeds

            self._seed_map = correction_seeds(self.field, self._h)
        return self._seed_map

    def _run(self, S: np.ndarray, seeds: np.ndarray, serial: bool) -> Correction:
        n = len(S)
        r, T, q = np.empty((n, 3)), np.empty((n, 3, 3)), np.empty((n, 4))
        converged, iterations = np.empty(n, dtype=bool), np.empty(n, dtype=np.int64)
        residual, mapped = np.empty(n), np.empty(n, dtype=bool)
        # an all-zero, denormal or huge matrix carries no pose: invalid, not a kernel division by zero
        finite = dipole.usable_signals(S)
        S = np.where(finite[:, None, None], S, np.eye(3))
        kernel = compiled.choose(_kernels.correct_serial if serial else _kernels.correct_kernel, n)
        use_map = self.use_seed_map and (self._seed_map is not None
                                         or (n >= SEED_MAP_FRAMES and not np.isfinite(seeds).all()))
        seed_map = self.seed_map().kernel_grid if use_map else _NO_MAP
        config = _kernels.Config(bool(use_map), int(self.max_iterations), STEP_TOLERANCE, float(self.max_residual))
        out = _kernels.Output(r, T, q, converged, iterations, residual, mapped)
        kernel(S, seeds, self._h, self.field.kernel_grid, seed_map, tuple(config), tuple(out))  # plain: kernels.py
        limit = self.residual_gate.limits(S, r)
        flags = (np.where(mapped, 0, OUTSIDE) | np.where(converged, 0, NOT_CONVERGED)
                 | np.where(residual <= limit, 0, HIGH_RESIDUAL)).astype(np.uint8)
        flags[~(np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(q), axis=1))] |= NOT_CONVERGED  # no pose came out
        flags[~finite] = INVALID_INPUT
        if not finite.all():
            r[~finite], q[~finite], residual[~finite] = np.nan, np.nan, np.nan
        if self.signal_noise is None:
            return Correction(r, q, flags, residual, iterations)
        precision, orientation_precision = self._precision(r, T)
        # where the pose's own residual says the table is off by more than the noise, the noise-only bound is widened
        widening = residual_widening(residual, S, float(self.signal_noise))
        precision *= widening
        orientation_precision *= widening
        self.gate.apply(precision, flags, finite)
        return Correction(r, q, flags, residual, iterations, precision, orientation_precision)

    def batch(self, S: np.ndarray, valid: np.ndarray | None = None, seeds: np.ndarray | None = None) -> Correction:
        """Correct signal matrices ``S`` (..., 3, 3), each frame on its own (no warm start unless ``seeds``,
        positions (..., 3) m). Samples with ``valid`` False are flagged INVALID_INPUT."""
        S = np.asarray(S, float)
        if S.shape[-2:] != (3, 3):
            raise InputError(f"signal matrices must have shape (..., 3, 3), got {S.shape}")
        lead = S.shape[:-2]
        flat = np.ascontiguousarray(S.reshape(-1, 3, 3))
        if valid is not None:
            flat = np.where(np.asarray(valid, bool).reshape(-1)[:, None, None], flat, np.nan)
        seed = np.full((len(flat), 3), np.nan) if seeds is None else np.ascontiguousarray(
            np.asarray(seeds, float).reshape(-1, 3))
        out = self._run(flat, seed, serial=len(flat) < 64)
        shaped = (None if a is None else a.reshape(lead) for a in (out.precision, out.orientation_precision))
        return Correction(out.position.reshape(*lead, 3), out.quaternion.reshape(*lead, 4), out.flags.reshape(lead),
                          out.residual.reshape(lead), out.iterations.reshape(lead), *shaped)

    def batch_poses(self, position: np.ndarray, quaternion: np.ndarray, valid: np.ndarray | None = None) -> Correction:
        """Correct tracker-reported poses: the signal is rebuilt as ``S = Tᵀ f_D(r)`` (docs/math.md §9)."""
        return self.batch(dipole.signal_from_pose(position, quaternion), valid)

    def update(self, S: np.ndarray, sensors: list | tuple | None = None) -> Correction:
        """Correct the latest frame of a stream: ``S`` (N, 3, 3), one per sensor, in one call.

        Each sensor is seeded by its own previous good pose (keyed by ``sensors``, default
        0..N−1) and falls back to a cold start when that fails.
        """
        S = np.ascontiguousarray(np.asarray(S, float).reshape(-1, 3, 3))
        keys = range(len(S)) if sensors is None else sensors
        seeds = np.array([self._previous.get(k, (np.nan, np.nan, np.nan)) for k in keys], dtype=float)
        out = self._run(S, seeds, serial=True)
        for n, key in enumerate(keys):
            if out.flags[n] == 0:
                self._previous[key] = out.position[n]
            else:
                self._previous.pop(key, None)
        return out

    def reset(self) -> None:
        """Forget every sensor's warm start (after a gap in the stream)."""
        self._previous.clear()
