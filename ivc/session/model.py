"""In-memory form of the session file (docs/session-format.md) and its validation.

A :class:`Session` is a set of protocol :class:`Step` recordings plus optional
:class:`Truth` for simulations. Validation raises :class:`SessionError` with the
HDF5 path of the offending dataset, what is wrong, and what to do about it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from ivc import rotations
from ivc.dipole import HEMISPHERES, closed_form_pose, signal_from_pose, usable_signals
from ivc.errors import SessionError

FORMAT_NAME = "session"
FORMAT_VERSION = 1

#: the protocol steps of Himberg 2010, ch. 4.4.3, in recording order
STEPS = ("cube_calibration", "cube_survey", "wand_calibration", "wand_sweep", "check")
#: the steps ``ivc fit`` needs; ``check`` is for ``ivc evaluate``
FIT_STEPS = STEPS[:4]
CUBE_SENSORS = 8
STEP_DESCRIPTIONS = {
    "cube_calibration": "interpolation cube, free space, static",
    "cube_survey": "interpolation cube at its declared pose in the distorted volume, static",
    "wand_calibration": "mapping wand, free space, static",
    "wand_sweep": "mapping wand, sensor 0 inside the cube, far end sweeping the distorted volume",
    "check": "independent poses in the distorted volume, for evaluation",
}
#: extension sweeps (after the wand sweep): ``extension_sweep_1`` … ``extension_sweep_99``, the wand
#: walked freely through the working volume with part of it inside the region mapped so far
EXTENSION_PREFIX = "extension_sweep_"
MAX_EXTENSION_SWEEPS = 99
EXTENSION_DESCRIPTION = "mapping wand walked freely through the working volume, part of it inside the mapped region"


def extension_step(number: int) -> str:
    """The step name of extension sweep ``number`` (1 … MAX_EXTENSION_SWEEPS)."""
    if not 1 <= int(number) <= MAX_EXTENSION_SWEEPS:
        raise SessionError(f"extension sweeps are numbered 1 to {MAX_EXTENSION_SWEEPS}, got {number}")
    return f"{EXTENSION_PREFIX}{int(number)}"


def is_extension_step(name: str) -> bool:
    """True for ``extension_sweep_N``, N = 1 … MAX_EXTENSION_SWEEPS (no leading zeros)."""
    number = name[len(EXTENSION_PREFIX):] if name.startswith(EXTENSION_PREFIX) else ""
    return number.isdigit() and not number.startswith("0") and 1 <= int(number) <= MAX_EXTENSION_SWEEPS


def extension_steps(names) -> list[str]:
    """The extension-sweep names among ``names``, in their numbered order."""
    return sorted((n for n in names if is_extension_step(n)), key=lambda n: int(n[len(EXTENSION_PREFIX):]))


#: the session's root attributes that declare the working volume to be mapped: an axis-aligned box,
#: its centre (3,) and size (3,) in metres, source frame (docs/session-format.md)
WORKING_VOLUME_ATTRS = ("working_volume_center", "working_volume_size")


def working_volume(attrs: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """The declared working volume ``(center (3,), size (3,))`` m of a session's root ``attrs``, or None
    when it declares none. Raises SessionError when only one of the two is given or either is malformed."""
    present = [key for key in WORKING_VOLUME_ATTRS if key in attrs]
    if not present:
        return None
    if len(present) == 1:
        missing = next(key for key in WORKING_VOLUME_ATTRS if key not in attrs)
        raise SessionError(f"/ attribute {present[0]} is given without {missing}: declare the working volume's "
                           "centre and size (m, source frame) together")
    center, size = (np.asarray(attrs[key], dtype=float).reshape(-1) for key in WORKING_VOLUME_ATTRS)
    if center.shape != (3,) or size.shape != (3,) or not (np.all(np.isfinite(center)) and np.all(size > 0)):
        raise SessionError(f"/ attributes {', '.join(WORKING_VOLUME_ATTRS)} must be three finite numbers and three "
                           f"positive sizes (m), got {attrs[WORKING_VOLUME_ATTRS[0]]!r} and "
                           f"{attrs[WORKING_VOLUME_ATTRS[1]]!r}")
    return center, size


def is_known_step(name: str) -> bool:
    """A step name of the format: one of STEPS or an extension sweep."""
    return name in STEPS or is_extension_step(name)


def step_order(name: str) -> tuple[int, int]:
    """Sort key of recording order: the protocol's steps, the extension sweeps after the wand sweep."""
    if is_extension_step(name):
        return STEPS.index("wand_sweep"), int(name[len(EXTENSION_PREFIX):])
    return (STEPS.index(name), 0) if name in STEPS else (len(STEPS), 0)


def describe_step(name: str) -> str:
    """One line saying what the step records."""
    return EXTENSION_DESCRIPTION if is_extension_step(name) else STEP_DESCRIPTIONS[name]


#: no AC electromagnetic tracker measures farther from its source than this, metres (long-range Polhemus
#: sources reach about 4.5 m): a position beyond it is in the wrong unit
PLAUSIBLE_RANGE_M = 5.0

#: unit quaternions are accepted within this much of norm 1
QUATERNION_NORM_TOLERANCE = 1e-6


#: the cube_survey attributes that declare the cube's pose (m; quaternion w, x, y, z)
DECLARED_POSE_ATTRS = ("declared_position", "declared_quaternion")


@dataclass(frozen=True)
class Lack:
    """One thing a session lacks before ``ivc fit`` can run."""

    step: str  # the protocol step it concerns
    short: str  # a few words, for a list: "no wand_sweep step"
    advice: str  # a whole sentence: what is missing and how to record it


@dataclass
class Truth:
    """True poses of a step (simulations and precision rigs only; never used to fit)."""

    position: NDArray[np.float64]  # (F, N, 3) metres, source frame
    quaternion: NDArray[np.float64]  # (F, N, 4) [w, x, y, z]


@dataclass
class Step:
    """One protocol step: F frames of N sensors.

    Holds ``signal`` (F, N, 3, 3), or ``position`` (F, N, 3, metres) with
    ``quaternion`` (F, N, 4), or both. ``valid`` (F, N) marks dropped or saturated
    samples False; non-finite values are allowed only there.
    """

    time: NDArray[np.float64]
    signal: NDArray[np.float64] | None = None
    position: NDArray[np.float64] | None = None
    quaternion: NDArray[np.float64] | None = None
    valid: NDArray[np.bool_] | None = None
    sample_rate_hz: float = 240.0
    sensor_ids: list[str] | None = None
    description: str = ""
    attrs: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(np.shape(self.time)[0])

    @property
    def n_sensors(self) -> int:
        data = self.signal if self.signal is not None else self.position
        shape = np.shape(data) if data is not None else ()
        return int(shape[1]) if len(shape) >= 2 else 0

    @property
    def valid_mask(self) -> NDArray[np.bool_]:
        """The samples to use: ``valid`` (all True when the step has none), and, in a step of signals, only where
        the signal matrix can be solved at all (:func:`ivc.dipole.usable_signals`: finite, neither all zeros nor
        denormal nor huge); the others are dropped, and flagged invalid input, like a sample marked invalid."""
        valid = (np.ones((self.n_frames, self.n_sensors), dtype=bool) if self.valid is None
                 else np.asarray(self.valid, dtype=bool))
        if self.signal is None or np.shape(self.signal) != valid.shape + (3, 3):
            return valid
        return valid & usable_signals(self.signal)

    @property
    def names(self) -> list[str]:
        return self.sensor_ids if self.sensor_ids is not None else [str(i) for i in range(self.n_sensors)]

    def select(self, frames: slice | NDArray) -> Step:
        """The same step restricted to some frames (a slice, indices or a boolean mask)."""
        cut = {k: (None if getattr(self, k) is None else getattr(self, k)[frames])
               for k in ("time", "signal", "position", "quaternion", "valid")}
        return replace(self, **cut)

    def signal_matrices(self) -> NDArray[np.float64]:
        """Signal matrices, rebuilt from the reported poses when the step has none (docs/math.md §9)."""
        if self.signal is not None:
            return self.signal
        with np.errstate(invalid="ignore", divide="ignore"):
            return signal_from_pose(self.position, self.quaternion)

    def poses(self, hemisphere: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Positions (F, N, 3) and quaternions (F, N, 4): the reported ones, or, when the step
        has signals only, their closed-form dipole solution (docs/math.md §3; exact in free space)."""
        if self.position is not None:
            return self.position, self.quaternion
        with np.errstate(invalid="ignore"):
            position, T = closed_form_pose(self.signal, hemisphere)
            return position, rotations.from_matrix(T)


@dataclass
class Session:
    """A whole session file: steps, truth, and the declared hemisphere."""

    hemisphere: str = "+x"
    steps: dict[str, Step] = field(default_factory=dict)
    truth: dict[str, Truth] = field(default_factory=dict)
    attrs: dict = field(default_factory=dict)

    def lacks_for_fit(self) -> list[Lack]:
        """What is still missing before ``ivc fit`` can run; empty when ready."""
        lacks = [Lack(name, f"no {name} step",
                      f"step {name!r} ({STEP_DESCRIPTIONS[name]}): record it with `ivc collect {name}`")
                 for name in FIT_STEPS if name not in self.steps]
        survey = self.steps.get("cube_survey")
        if survey is not None and not set(DECLARED_POSE_ATTRS) <= survey.attrs.keys():
            lacks.append(Lack("cube_survey", "no declared cube pose in cube_survey",
                              "cube_survey has no declared cube pose (attributes declared_position, "
                              "declared_quaternion): record it again with `ivc collect cube_survey "
                              "--declared-position x,y,z --declared-quaternion w,x,y,z`"))
        return lacks

    def missing_for_fit(self) -> list[str]:
        """:meth:`lacks_for_fit` as sentences that say what to do."""
        return [lack.advice for lack in self.lacks_for_fit()]

    def select_frames(self, step: str, frames: slice | NDArray) -> Session:
        """A copy in which ``step`` (and its truth) keeps only some frames."""
        steps = dict(self.steps, **{step: self.steps[step].select(frames)})
        truth = dict(self.truth)
        if step in truth:
            truth[step] = Truth(truth[step].position[frames], truth[step].quaternion[frames])
        return Session(self.hemisphere, steps, truth, self.attrs)

    def validate(self) -> None:
        """Raise :class:`SessionError` for anything that breaks the format."""
        if self.hemisphere not in HEMISPHERES:
            raise SessionError(f"/ attribute hemisphere = {self.hemisphere!r}: must be one of {', '.join(HEMISPHERES)}")
        for name, step in self.steps.items():
            validate_step(name, step)
        for name, truth in self.truth.items():
            if name not in self.steps:
                raise SessionError(f"/truth/{name}: truth for a step the session does not have")
            validate_truth(name, truth, self.steps[name])
        calibration = self.steps.get("wand_calibration")
        for name in ["wand_sweep", *extension_steps(self.steps)]:
            sweep = self.steps.get(name)
            if calibration is not None and sweep is not None and calibration.n_sensors != sweep.n_sensors:
                raise SessionError(
                    f"/steps/{name}: {sweep.n_sensors} sensors but wand_calibration has "
                    f"{calibration.n_sensors}; both steps must record the same wand"
                )


def _check_shape(path: str, array, shape: tuple) -> np.ndarray:
    """``array`` as float64 with ``shape`` (None entries free), or a SessionError naming ``path``."""
    a = np.asarray(array)
    if a.dtype.kind not in "fiu":
        raise SessionError(f"{path}: expected numbers, got dtype {a.dtype}")
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape, strict=True)):
        want = "(" + ", ".join("any" if s is None else str(s) for s in shape) + ")"
        raise SessionError(f"{path}: shape {a.shape}, expected {want}")
    return a


def _check_finite(path: str, a: np.ndarray, valid: np.ndarray) -> None:
    bad = ~np.isfinite(a).reshape(a.shape[:2] + (-1,)).all(axis=-1) & valid
    if bad.any():
        frame, sensor = np.argwhere(bad)[0]
        raise SessionError(
            f"{path}: {int(bad.sum())} valid samples hold NaN or inf (first at frame {frame}, sensor {sensor}); "
            "mark dropped samples with valid = False"
        )


def _check_unit_quaternions(path: str, q: np.ndarray, valid: np.ndarray) -> None:
    with np.errstate(invalid="ignore"):
        off = np.abs(np.linalg.norm(q, axis=-1) - 1.0)
    bad = (off > QUATERNION_NORM_TOLERANCE) & valid
    if bad.any():
        raise SessionError(
            f"{path}: {int(bad.sum())} quaternions are not unit norm (off by up to {off[bad].max():.3g}); "
            "quaternions are [w, x, y, z] and must be normalised"
        )


def validate_step(name: str, step: Step) -> None:
    """Check one step against the format; raise :class:`SessionError` naming the dataset."""
    base = f"/steps/{name}"
    if not is_known_step(name):
        raise SessionError(f"{base}: unknown step; the steps are {', '.join(STEPS)} and "
                           f"{EXTENSION_PREFIX}1 … {EXTENSION_PREFIX}{MAX_EXTENSION_SWEEPS}")
    time = _check_shape(f"{base}/time", step.time, (None,))
    frames = time.shape[0]
    if frames == 0:
        raise SessionError(f"{base}/time: the step has no frames")
    if not np.all(np.isfinite(time)):
        raise SessionError(f"{base}/time: holds NaN or inf")
    if np.any(np.diff(time) < 0):
        raise SessionError(f"{base}/time: goes backwards at frame {int(np.argmax(np.diff(time) < 0)) + 1}")
    if np.any(np.diff(time) == 0):
        raise SessionError(f"{base}/time: frame {int(np.argmax(np.diff(time) == 0)) + 1} repeats the time of the "
                           "frame before; each frame needs its own time")
    if step.signal is None and step.position is None and step.quaternion is None:
        raise SessionError(f"{base}: holds neither signal nor position + quaternion")
    if (step.position is None) != (step.quaternion is None):
        missing = "quaternion" if step.quaternion is None else "position"
        raise SessionError(f"{base}/{missing}: missing; a reported pose needs both position and quaternion")
    for dataset, tail in (("signal", (3, 3)), ("position", (3,)), ("quaternion", (4,))):
        value = getattr(step, dataset)
        if value is not None and np.ndim(value) != 2 + len(tail):
            wanted = ", ".join(["frames", "sensors", *map(str, tail)])
            raise SessionError(f"{base}/{dataset}: shape {np.shape(value)}, expected ({wanted})")
    sensors = step.n_sensors
    if step.valid is None:
        valid = np.ones((frames, sensors), dtype=bool)
    else:
        valid = np.asarray(step.valid)
        if valid.dtype != bool:
            raise SessionError(f"{base}/valid: dtype {valid.dtype}, expected bool")
        if valid.ndim >= 1 and valid.shape[0] != frames:
            raise SessionError(f"{base}/valid: {valid.shape[0]} frames but time has {frames}")
        if valid.shape != (frames, sensors):
            raise SessionError(f"{base}/valid: shape {valid.shape}, expected ({frames}, {sensors}) like the data")
    for dataset, tail in (("signal", (3, 3)), ("position", (3,)), ("quaternion", (4,))):
        value = getattr(step, dataset)
        if value is None:
            continue
        a = np.asarray(value)
        if a.ndim >= 1 and a.shape[0] != frames:
            raise SessionError(f"{base}/{dataset}: {a.shape[0]} frames but time has {frames}")
        a = _check_shape(f"{base}/{dataset}", a, (frames, sensors) + tail)
        _check_finite(f"{base}/{dataset}", a, valid)
    if step.quaternion is not None:
        _check_unit_quaternions(f"{base}/quaternion", np.asarray(step.quaternion), valid)
    if step.position is not None:
        _check_range(f"{base}/position", np.asarray(step.position), valid)
    if name.startswith("cube_") and sensors != CUBE_SENSORS:
        raise SessionError(f"{base}: {sensors} sensors; the interpolation cube has {CUBE_SENSORS}")
    if not (np.isfinite(step.sample_rate_hz) and step.sample_rate_hz > 0):
        raise SessionError(f"{base} attribute sample_rate_hz = {step.sample_rate_hz}: must be a positive rate in Hz")
    if step.sensor_ids is not None and (len(step.sensor_ids) != sensors or len(set(step.sensor_ids)) != sensors):
        raise SessionError(f"{base} attribute sensor_ids: needs {sensors} distinct names, got {list(step.sensor_ids)}")
    if name == "cube_survey":
        _validate_declared_pose(base, step.attrs)


def _check_range(path: str, position: np.ndarray, valid: np.ndarray) -> None:
    """Refuse valid positions beyond any AC tracker's range: a length unit read wrong (inches or millimetres
    taken for metres)."""
    distance = np.where(valid, np.linalg.norm(position, axis=-1), 0.0)
    if distance.max(initial=0.0) > PLAUSIBLE_RANGE_M:
        frame, sensor = np.unravel_index(int(np.argmax(distance)), distance.shape)
        raise SessionError(f"{path}: frame {frame}, sensor {sensor} is {distance[frame, sensor]:.3g} m from the "
                           f"source, beyond any AC tracker's range ({PLAUSIBLE_RANGE_M:g} m): positions are in "
                           "metres; were they read in another unit (inches, centimetres, millimetres)?")


def _validate_declared_pose(base: str, attrs: dict) -> None:
    for key, size in (("declared_position", 3), ("declared_quaternion", 4)):
        if key not in attrs:
            raise SessionError(
                f"{base} attribute {key}: missing; the cube survey needs the cube's declared pose in the source frame"
            )
        value = np.asarray(attrs[key], dtype=float)
        if value.shape != (size,) or not np.all(np.isfinite(value)):
            raise SessionError(f"{base} attribute {key}: expected {size} finite numbers, got {value}")
    if abs(np.linalg.norm(attrs["declared_quaternion"]) - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise SessionError(f"{base} attribute declared_quaternion: not a unit quaternion")
    distance = float(np.linalg.norm(attrs["declared_position"]))
    if distance > PLAUSIBLE_RANGE_M:
        position = np.asarray(attrs["declared_position"], dtype=float)
        raise SessionError(f"{base} attribute declared_position: {distance:.3g} m from the source, beyond any AC "
                           f"tracker's range ({PLAUSIBLE_RANGE_M:g} m); it is in metres: if these are millimetres, "
                           f"use {', '.join(f'{v / 1000:g}' for v in position)}")


def validate_truth(name: str, truth: Truth, step: Step) -> None:
    base = f"/truth/{name}"
    shape = (step.n_frames, step.n_sensors)
    position = _check_shape(f"{base}/position", truth.position, shape + (3,))
    quaternion = _check_shape(f"{base}/quaternion", truth.quaternion, shape + (4,))
    everywhere = np.ones(shape, dtype=bool)
    _check_finite(f"{base}/position", position, everywhere)
    _check_finite(f"{base}/quaternion", quaternion, everywhere)
    _check_unit_quaternions(f"{base}/quaternion", quaternion, everywhere)
