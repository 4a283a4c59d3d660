"""The tracker's own source and sensor model (docs/tracker.md).

A real tracker's coils are not three perfect, concentric, orthogonal unit dipoles. Here
source coil ``i`` is a point dipole of moment ``a_i`` (column ``i`` of ``source_moments``,
source frame) at ``p_i`` (row ``i`` of ``source_offsets``, metres, source frame), and
sensor coil ``j`` picks up the field along ``b_j`` (column ``j`` of ``sensor_moments``,
sensor frame) at ``q_j`` (row ``j`` of ``sensor_offsets``, metres, sensor frame). For a
sensor at ``r`` with orientation ``T`` (columns = sensor axes in the source frame) the
signal matrix (row = sensor coil, column = source coil) is::

    S[j, i] = (T b_j)ᵀ f_D(T q_j + r − p_i) a_i

With concentric coils (all offsets zero) this is ``S = Bᵀ Tᵀ f_D(r) A``, so the
gain-corrected signal ``B⁻ᵀ S A⁻¹`` is the ideal ``Tᵀ f_D(r)``. The ideal tracker
(``A = B = I``, no offsets, :meth:`Tracker.ideal`) is the default everywhere, and for
it every function here returns exactly what :func:`ivc.dipole.signal` returns.

The tracker file (:func:`save_tracker`, :func:`load_tracker`) is JSON, versioned.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from ivc.dipole.field import field as dipole_field
from ivc.dipole.field import field_jacobian, flat_poses, signal
from ivc.errors import TrackerError

__all__ = ["DEFAULT_RESIDUAL_GATE", "GATE_FACTOR", "MIN_RESIDUAL_GATE", "TRACKER_FORMAT", "TRACKER_VERSION", "Tracker",
           "load_tracker", "save_tracker"]

TRACKER_FORMAT = "ivc-tracker"
TRACKER_VERSION = 1
#: the pose gate of a model without a calibrated one: relative residual ‖S − S_model‖_F / ‖S‖_F
DEFAULT_RESIDUAL_GATE = 0.01
#: a calibrated gate is this many times the model's own 99th-percentile residual (and the noise's)
GATE_FACTOR = 3.0
#: the smallest calibrated gate (a model fitted to noise-free simulations would otherwise gate at rounding)
MIN_RESIDUAL_GATE = 1e-4


def _matrix(value, name: str) -> np.ndarray:
    a = np.array(value, dtype=float)
    if a.shape != (3, 3):
        raise TrackerError(f"{name} must be a 3x3 matrix, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise TrackerError(f"{name} holds non-finite values")
    return a


@dataclass
class Tracker:
    """Source and sensor coil model; the default is the ideal tracker.

    ``source_moments`` (3, 3): column ``i`` is source coil ``i``'s moment (source frame,
    in the units that make the ideal tracker's signal ``Tᵀ f_D(r)``). ``sensor_moments``
    (3, 3): column ``j`` is sensor coil ``j``'s effective area-gain vector (sensor frame).
    ``source_offsets`` (3, 3): row ``i`` is source coil ``i``'s centre, metres, source
    frame. ``sensor_offsets`` (3, 3): row ``j`` is sensor coil ``j``'s centre, metres,
    sensor frame. ``calibration`` holds what a calibration recorded (free-form).
    """

    source_moments: np.ndarray = field(default_factory=lambda: np.eye(3))
    sensor_moments: np.ndarray = field(default_factory=lambda: np.eye(3))
    source_offsets: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    sensor_offsets: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    calibration: dict = field(default_factory=dict)
    bias: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    position_correction: np.ndarray = field(default_factory=lambda: np.zeros((3, 4)))
    rotation_correction: np.ndarray = field(default_factory=lambda: np.zeros((3, 4)))
    residual_gate: float | None = None
    hemisphere: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.source_moments = _matrix(self.source_moments, "source_moments")
        self.sensor_moments = _matrix(self.sensor_moments, "sensor_moments")
        self.source_offsets = _matrix(self.source_offsets, "source_offsets")
        self.sensor_offsets = _matrix(self.sensor_offsets, "sensor_offsets")
        self.bias = _matrix(self.bias, "bias")
        for name in ("position_correction", "rotation_correction"):
            value = np.array(getattr(self, name), dtype=float)
            if value.shape != (3, 4) or not np.all(np.isfinite(value)):
                raise TrackerError(f"{name} must be a finite 3x4 matrix, got shape {value.shape}")
            setattr(self, name, value)
        for name in ("source_moments", "sensor_moments"):
            if not np.linalg.cond(getattr(self, name)) < 1e10:
                raise TrackerError(f"{name} is singular: three coils must span three directions")
        if self.residual_gate is not None:
            self.residual_gate = float(self.residual_gate)
            if not (math.isfinite(self.residual_gate) and self.residual_gate > 0):
                raise TrackerError(f"residual_gate must be a fraction > 0, got {self.residual_gate}")
        if self.hemisphere is not None:
            h = np.array(self.hemisphere, dtype=float)
            if h.shape != (3,) or not np.all(np.isfinite(h)) or not np.linalg.norm(h) > 0:
                raise TrackerError(f"hemisphere must be a non-zero 3-vector, got {self.hemisphere!r}")
            self.hemisphere = h / np.linalg.norm(h)

    @classmethod
    def ideal(cls) -> Tracker:
        """Three perfect, concentric, orthogonal unit coils in source and sensor."""
        return cls()

    @property
    def is_ideal(self) -> bool:
        return (np.array_equal(self.source_moments, np.eye(3)) and np.array_equal(self.sensor_moments, np.eye(3))
                and self.is_concentric and not np.any(self.bias) and not self.has_output_correction)

    @property
    def has_output_correction(self) -> bool:
        return bool(np.any(self.position_correction) or np.any(self.rotation_correction))

    def correct_pose(self, r: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Apply the output correction to solved poses (F, 3) m, (F, 3, 3).

        ``r' = r + W_p [r; 1]`` and ``T' = exp([W_r [r; 1]]×) T``: a correction affine in
        position of what the coil model leaves (fitted on the calibration points).
        """
        if not self.has_output_correction:
            return r, T
        from ivc import rotations

        h = np.concatenate([r, np.ones(r.shape[:-1] + (1,))], axis=-1)
        dr = h @ self.position_correction.T
        dw = h @ self.rotation_correction.T
        return r + dr, rotations.to_matrix(rotations.from_rotvec(dw)) @ T

    def pose_gate(self, noise_relative: float = 0.0) -> float:
        """The largest relative residual ``‖S − S_model‖_F / ‖S‖_F`` of a right pose under this model.

        :attr:`residual_gate` (a calibration sets it from its own residue; :data:`DEFAULT_RESIDUAL_GATE`
        without one), combined with ``GATE_FACTOR · √3 · noise_relative`` for signals whose per-entry
        noise is ``noise_relative`` of ``‖S‖₂`` where the caller knows it (a six-parameter fit of
        nine entries leaves at most ``√3`` of that, relative to ``‖S‖_F``).
        """
        if not (math.isfinite(noise_relative) and noise_relative >= 0):
            raise TrackerError(f"noise_relative must be a fraction >= 0, got {noise_relative}")
        own = self.residual_gate if self.residual_gate is not None else DEFAULT_RESIDUAL_GATE
        return float(math.hypot(own, GATE_FACTOR * math.sqrt(3.0) * noise_relative))

    @property
    def is_concentric(self) -> bool:
        return not (np.any(self.source_offsets) or np.any(self.sensor_offsets))

    # --- signal model -------------------------------------------------------------------------

    def signal(self, r: ArrayLike, T: ArrayLike) -> np.ndarray:
        """Signal matrices (..., 3, 3) of sensors at ``r`` (..., 3) m with orientations ``T`` (..., 3, 3).

        The ideal tracker returns :func:`ivc.dipole.signal` (bit for bit).
        """
        if self.is_ideal:
            return signal(r, T)
        r_flat, T_flat, lead = flat_poses(r, T)
        if self.is_concentric:
            S = np.swapaxes(self.sensor_moments, 0, 1) @ signal(r_flat, T_flat) @ self.source_moments + self.bias
        else:
            S = model(T_flat, r_flat, self)[0]
        return S.reshape(lead + (3, 3))

    def corrected(self, S: ArrayLike) -> np.ndarray:
        """Gain-corrected signal ``B⁻ᵀ S A⁻¹`` (..., 3, 3): the ideal ``Tᵀ f_D(r)`` for concentric coils."""
        S = np.asarray(S, dtype=float)
        if S.shape[-2:] != (3, 3):
            raise TrackerError(f"signal matrices must have shape (..., 3, 3), got {S.shape}")
        if self.is_ideal:
            return S.copy()
        return np.linalg.inv(self.sensor_moments).T @ (S - self.bias) @ np.linalg.inv(self.source_moments)

    def pose_jacobian(self, r: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``S`` (F, 3, 3) and ``∂S/∂(r, ω)`` (F, 3, 3, 6) with ``T ← T exp([ω]×)``, ``r ← r + δr``."""
        S, parts = model(np.asarray(T, float), np.asarray(r, float), self, parts=True)
        return S, np.concatenate([parts.d_t, parts.d_w], axis=-1)

    # --- file --------------------------------------------------------------------------------

    def to_dict(self) -> dict:
        return {
            "format": TRACKER_FORMAT,
            "version": TRACKER_VERSION,
            "units": {"moments": "ideal dipole units (signal = T^T f_D(r) for the ideal tracker)",
                      "offsets": "m"},
            "source_moments": self.source_moments.tolist(),
            "sensor_moments": self.sensor_moments.tolist(),
            "source_offsets": self.source_offsets.tolist(),
            "sensor_offsets": self.sensor_offsets.tolist(),
            "bias": self.bias.tolist(),
            "position_correction": self.position_correction.tolist(),
            "rotation_correction": self.rotation_correction.tolist(),
            "residual_gate": self.residual_gate,
            "hemisphere": None if self.hemisphere is None else self.hemisphere.tolist(),
            "calibration": self.calibration,
        }

    @classmethod
    def from_dict(cls, data: dict, where: str = "tracker") -> Tracker:
        if not isinstance(data, dict) or data.get("format") != TRACKER_FORMAT:
            raise TrackerError(f"{where}: not an ivc tracker file (no \"format\": \"{TRACKER_FORMAT}\")")
        version = data.get("version")
        if version != TRACKER_VERSION:
            raise TrackerError(f"{where}: tracker file version {version!r}; this ivc reads version "
                               f"{TRACKER_VERSION}: upgrade ivc or recalibrate")
        missing = [k for k in ("source_moments", "sensor_moments") if k not in data]
        if missing:
            raise TrackerError(f"{where}: missing {', '.join(missing)}")
        try:
            return cls(data["source_moments"], data["sensor_moments"], data.get("source_offsets", np.zeros((3, 3))),
                       data.get("sensor_offsets", np.zeros((3, 3))), dict(data.get("calibration", {})),
                       data.get("bias", np.zeros((3, 3))), data.get("position_correction", np.zeros((3, 4))),
                       data.get("rotation_correction", np.zeros((3, 4))), data.get("residual_gate"),
                       data.get("hemisphere"))
        except TrackerError as error:
            raise TrackerError(f"{where}: {error}") from None
        except (TypeError, ValueError) as error:
            raise TrackerError(f"{where}: malformed entry ({error})") from None


def save_tracker(tracker: Tracker, path: str | Path) -> None:
    """Write ``tracker`` as a JSON tracker file, atomically (the old file survives any failure)."""
    from ivc.files import atomic_path

    text = json.dumps(_finite_json(tracker.to_dict()), indent=2)
    # one line per matrix row: innermost lists of numbers on one line (JSON strings hold no raw newline)
    text = re.sub(r"\[\n\s+([-+0-9.eE,\s]+?)\n\s*\]", lambda m: "[" + " ".join(m.group(1).split()) + "]", text)
    with atomic_path(path) as tmp:
        tmp.write_text(text + "\n", encoding="utf-8")


def load_tracker(path: str | Path) -> Tracker:
    """Read a tracker file written by :func:`save_tracker`."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as error:
        raise TrackerError(f"{path}: not a JSON tracker file ({error})") from None
    except UnicodeDecodeError:
        raise TrackerError(f"{path}: a binary file, not a tracker file (a JSON file written by `ivc tracker "
                           "calibrate`); is it a session or a table?") from None
    return Tracker.from_dict(data, str(path))


def _finite_json(value):
    """JSON-safe copy: NumPy scalars and arrays become lists, NaN becomes None."""
    if isinstance(value, dict):
        return {str(k): _finite_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return _finite_json(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


# --- the model and its analytic derivatives ---------------------------------------------------


@dataclass
class ModelParts:
    """Derivatives of ``S[n, j, i]`` (sensor coil j, source coil i) of :func:`model`.

    ``d_A[n, j, i, l]`` = ∂S/∂A[l, i]; ``d_B[n, j, i, k]`` = ∂S/∂B[k, j]; ``d_p[n, j, i, m]`` =
    ∂S/∂p_i[m]; ``d_q[n, j, i, m]`` = ∂S/∂q_j[m]; ``d_t`` (position, source frame) and
    ``d_w`` (rotation increment ``T ← T exp([ω]×)``) and ``d_v`` (translation increment in the
    sensor frame, ``r ← r + T v``), each (N, 3, 3, 3).
    """

    d_A: np.ndarray
    d_B: np.ndarray
    d_p: np.ndarray
    d_q: np.ndarray
    d_t: np.ndarray
    d_w: np.ndarray
    d_v: np.ndarray


def model(R: np.ndarray, t: np.ndarray, tracker: Tracker, parts: bool = False):
    """``S`` (N, 3, 3) of sensors at ``t`` (N, 3) m with orientations ``R`` (N, 3, 3); with ``parts``
    also its derivatives (:class:`ModelParts`)."""
    A, B, p, q = tracker.source_moments, tracker.sensor_moments, tracker.source_offsets, tracker.sensor_offsets
    u = R @ B  # column j: sensor coil j's axis in the source frame
    w = np.einsum("nab,jb->nja", R, q)  # sensor coil centres, rotated
    x = w[:, :, None, :] + t[:, None, None, :] - p[None, None, :, :]  # (N, j, i, 3): coil-to-coil vectors
    F = dipole_field(x)  # (N, j, i, 3, 3)
    Fa = np.einsum("njikl,li->njik", F, A)  # field of source coil i at sensor coil j
    S = np.einsum("nkj,njik->nji", u, Fa) + tracker.bias
    if not parts:
        return S, None
    dF = field_jacobian(x)  # (N, j, i, k, l, m)
    G = np.einsum("nkj,njiklm,li->njim", u, dF, A)  # ∂S/∂x
    FaS = np.einsum("nkc,njik->njic", R, Fa)  # in the sensor frame
    GS = np.einsum("nmc,njim->njic", R, G)
    d_A = np.einsum("nkj,njikl->njil", u, F)
    d_w = np.cross(B.T[None, :, None, :], FaS) + np.cross(q[None, :, None, :], GS)
    return S, ModelParts(d_A=d_A, d_B=FaS, d_p=-G, d_q=GS, d_t=G, d_w=d_w, d_v=GS)
