"""Stop rules of guided collection: when a protocol step has recorded enough, in numbers a person can watch.

Each rule reads the step's frames batch by batch (:meth:`StopRule.update`) and says where it stands
(:meth:`StopRule.state`): progress toward its targets, the problems it sees, the region still thin, and whether
it is done. It decides nothing about which frames are stored (every frame is kept as recorded), with one
exception stated in its output: a static fixture that moves restarts its step (:class:`StaticRule`), since
frames of two placements must not be averaged.

- :class:`StaticRule` (cube_calibration, cube_survey, wand_calibration): the standard error of each sensor's
  mean position and orientation below a stated bound, at least the method's minimum frames, nothing moved.
- :class:`SweepRule` (wand_sweep): samples that pass the fixtures' own gates (:func:`ivc.fixtures.mapping.map_sweep`
  with the calibrations already in the session: sensor 0 converged inside the cube, residual, estimated error),
  the coverage of the mapped ball by octant and of the wand's directions; names the thinnest region.
- :class:`ExtensionRule` (extension sweeps): the share of the declared working volume the wand came near, by face.
- :class:`CountRule` (check, or any step given a frame count or a duration): frames or seconds of tracker time.

Units: metres, radians and seconds of the source's clock; positions in the source frame.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from ivc import rotations
from ivc.collect.checks import DEFAULT_MIN_FRAMES, MIN_FRAMES, STATIC_STEPS
from ivc.errors import InputError, IvcError
from ivc.fixtures.volume import FACES, box_points, face_shares
from ivc.session import Session, Step, is_extension_step, working_volume

#: static steps: bound on the standard error of each sensor's mean position (m) and orientation (rad): a tenth
#: of the accuracy a fitted map reaches on the default scene (0.04-0.06 mm, 0.17-0.23 mrad median; docs/collect.md)
STATIC_POSITION_SE = 5e-6
STATIC_ANGLE_SE = 2e-5
#: a static fixture has moved when a sensor is this far from its mean pose (the checks' spread bound) ...
MOVED_POSITION = 0.002  # m
MOVED_ANGLE = 0.02  # rad
#: ... in this many consecutive frames (one glitching frame is not a bump)
MOVED_FRAMES = 3
#: wand sweep: kept wand samples (frames x sensors that pass the gates) wanted in all
SWEEP_MIN_KEPT = 50_000
#: kept samples wanted in the outer half of each octant of the mapped ball
SWEEP_PER_OCTANT = 2_000
#: the wand's axis directions are binned into this many near-equal cells of the sphere (each ~36 deg across) ...
DIRECTION_BINS = 32
#: ... and each wants this many frames whose sensor 0 passed the gates
SWEEP_PER_DIRECTION = 200
#: a wand sensor whose reported distance from sensor 0 is off its calibrated lever arm by more than this (m, median
#: over a second; the room's distortion moves reported positions by millimetres) is said to break the wand's rigidity
RIGIDITY_TOLERANCE = 0.015
#: frames solved through the cube at once (1 s at 240 Hz): the gates run on this many frames together
SWEEP_CHUNK = 240
#: extension sweeps: the lattice (m) probing the working volume, and how near (m) a wand sensor must come to a
#: lattice point to cover it (the map's cells interpolate between samples a few centimetres apart)
EXTENSION_STEP = 0.02
EXTENSION_REACH = 0.04
#: the share of the working volume, and of each face's 5 cm layer, an extension sweep aims for
EXTENSION_SHARE = 0.95
EXTENSION_FACE_SHARE = 0.90
#: the check step's frames when no count or duration is given (the simulator's default)
CHECK_FRAMES = 10_000
#: an extension sweep or a check kept after a Ctrl-C needs at least this many frames
MIN_KEPT_FRAMES = DEFAULT_MIN_FRAMES

OCTANT_NAMES = tuple(f"{'+' if n & 4 else '-'}x {'+' if n & 2 else '-'}y {'+' if n & 1 else '-'}z" for n in range(8))


@dataclass(frozen=True)
class Frames:
    """A batch of B frames of N sensors, as the rules read it: source times (B,) s, ``valid`` (B, N), positions
    (B, N, 3) m and quaternions (B, N, 4) (reported, or the closed-form solution of the signals; NaN where
    invalid), and the signals (B, N, 3, 3) where the source sends them."""

    time: NDArray[np.float64]
    valid: NDArray[np.bool_]
    position: NDArray[np.float64]
    quaternion: NDArray[np.float64]
    signal: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.time)

    def select(self, frames: slice) -> Frames:
        return Frames(self.time[frames], self.valid[frames], self.position[frames], self.quaternion[frames],
                      None if self.signal is None else self.signal[frames])

    def as_step(self) -> Step:
        return Step(time=self.time, signal=self.signal, position=self.position, quaternion=self.quaternion,
                    valid=self.valid)


@dataclass(frozen=True)
class Progress:
    """One number a rule watches: ``value`` against ``target`` in ``unit`` (``at_most``: the value must come down
    to the target, as a standard error does; else it must reach it, as a count does)."""

    label: str
    value: float
    target: float
    unit: str = ""
    at_most: bool = False

    @property
    def done(self) -> bool:
        return bool(self.value <= self.target) if self.at_most else bool(self.value >= self.target)

    @property
    def fraction(self) -> float:
        """0-1 toward the target (for a progress bar)."""
        if self.done:
            return 1.0
        if self.at_most:
            return float(np.clip(self.target / self.value, 0.0, 1.0)) if self.value > 0 else 1.0
        return float(np.clip(self.value / self.target, 0.0, 1.0)) if self.target > 0 else 1.0


@dataclass
class RuleState:
    """Where a rule stands: ``done`` when every target is met; ``progress`` the numbers; ``problems`` in plain
    words; ``thin`` the region still short of its target, in words (None when none is); ``target`` a point (3,) m
    to go to next (for the 3D view); ``points`` the sample positions (M, 3) m so far (a bounded subsample);
    ``cells`` the coverage regions as (centre (3,) m, share 0-1 of their target) pairs."""

    done: bool
    progress: list[Progress]
    problems: list[str] = field(default_factory=list)
    thin: str | None = None
    target: NDArray[np.float64] | None = None
    points: NDArray[np.float64] | None = None
    cells: list[tuple[NDArray[np.float64], float]] = field(default_factory=list)


class StopRule(Protocol):
    """What guided collection asks of a stop rule. ``description`` states it in words (shown to the user)."""

    description: str

    def update(self, frames: Frames) -> int | None:
        """Read a batch; return the batch index from which the step starts again (its earlier frames, and
        all recorded before, are to be dropped: a static fixture moved), else None."""

    def finish(self) -> None:
        """Account for frames held back for a batched computation (the step is ending)."""

    def state(self) -> RuleState: ...

    def usable(self) -> tuple[bool, str]:
        """Whether what was recorded so far makes a valid step, and why (in words)."""


class _Reservoir:
    """Up to ``size`` points (3,) kept as a uniform subsample of all those offered (for the 3D view)."""

    def __init__(self, size: int = 4000, seed: int = 0):
        self.size = size
        self.points = np.empty((0, 3))
        self.seen = 0
        self._rng = np.random.default_rng(seed)

    def add(self, points: NDArray[np.float64]) -> None:
        points = points[np.all(np.isfinite(points), axis=1)]
        if not len(points):
            return
        room = self.size - len(self.points)
        if room > 0:
            self.points = np.concatenate([self.points, points[:room]])
            self.seen += min(room, len(points))
            points = points[room:]
        if len(points):  # reservoir sampling, vectorised: point i of the stream replaces a slot with prob size/i
            index = self.seen + np.arange(1, len(points) + 1)
            slot = (self._rng.random(len(points)) * index).astype(int)
            take = slot < self.size
            self.points[slot[take]] = points[take]
            self.seen += len(points)


def fixture_name(step: str) -> str:
    return "the cube" if step.startswith("cube") else "the wand" if step.startswith("wand") else "the fixture"


class StaticRule:
    """A static step is done when, for every sensor, the standard error of its mean position is at most
    ``position_se`` m and of its mean orientation at most ``angle_se`` rad, over at least ``min_frames`` valid
    frames recorded since the fixture last moved.

    The fixture has moved when a sensor's pose is more than ``moved_position`` m or ``moved_angle`` rad from its
    mean in ``moved_frames`` consecutive frames: the step then starts again from the frame where it moved
    (:meth:`update` returns that frame), so two placements are never averaged. The standard error is the sample
    spread over √n: it assumes uncorrelated frames (docs/collect.md)."""

    def __init__(self, step: str, position_se: float = STATIC_POSITION_SE, angle_se: float = STATIC_ANGLE_SE,
                 min_frames: int | None = None, moved_position: float = MOVED_POSITION,
                 moved_angle: float = MOVED_ANGLE, moved_frames: int = MOVED_FRAMES):
        self.step = step
        self.position_se, self.angle_se = float(position_se), float(angle_se)
        self.min_frames = int(MIN_FRAMES.get(step, DEFAULT_MIN_FRAMES) if min_frames is None else min_frames)
        self.moved_position, self.moved_angle, self.moved_frames = float(moved_position), float(moved_angle), \
            int(moved_frames)
        self.restarts = 0
        self.last_move: str | None = None
        self._n: NDArray[np.float64] | None = None
        self.description = (f"{step}: stops when every sensor's mean pose has a standard error of at most "
                            f"{1e3 * self.position_se:.3g} mm and {1e3 * self.angle_se:.3g} mrad over at least "
                            f"{self.min_frames} frames, and {fixture_name(step)} has not moved (more than "
                            f"{1e3 * self.moved_position:.3g} mm or {1e3 * self.moved_angle:.3g} mrad from its mean "
                            f"in {self.moved_frames} frames running: the step then starts again)")

    def _reset(self, n_sensors: int) -> None:
        self._n = np.zeros(n_sensors)
        self._sum = np.zeros((n_sensors, 3))
        self._squares = np.zeros((n_sensors, 3))
        self._turn = np.zeros((n_sensors, 3))
        self._turn_squares = np.zeros((n_sensors, 3))
        self._reference = np.full((n_sensors, 4), np.nan)  # each sensor's first valid pose in the segment
        self._origin = np.full((n_sensors, 3), np.nan)
        self._run = 0
        self._frames = 0  # frames of the segment (since the fixture was last still)

    def update(self, frames: Frames) -> int | None:
        if self._n is None or len(self._n) != frames.valid.shape[1]:
            self._reset(frames.valid.shape[1])
        restart = None
        offset = 0
        while True:
            moved = self._accumulate(frames.select(slice(offset, None)))
            if moved is None:
                return restart
            offset += moved
            restart = offset
            self.restarts += 1
            self._reset(frames.valid.shape[1])

    def _accumulate(self, frames: Frames) -> int | None:
        """Add a batch to the segment's sums; the batch index at which the fixture moved (nothing of the batch
        from there on is added), else None."""
        valid = frames.valid & np.all(np.isfinite(frames.position), axis=-1) & np.all(
            np.isfinite(frames.quaternion), axis=-1)
        if not len(frames):
            return None
        unset = np.isnan(self._reference[:, 0]) & valid.any(axis=0)
        if unset.any():  # a sensor's first valid frame in the segment is its reference
            first = np.argmax(valid, axis=0)[unset]
            self._reference[unset] = frames.quaternion[first, np.flatnonzero(unset)]
            self._origin[unset] = frames.position[first, np.flatnonzero(unset)]
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a sensor with no valid frame in the batch
            start = np.nanmedian(np.where(valid[..., None], frames.position, np.nan), axis=0)
        start = np.where(np.isfinite(start), start, self._origin)
        # the segment's mean so far, or at its start the batch's median (one noisy first frame is no reference)
        reference = np.where(self._n[:, None] > 0, self._sum / np.maximum(self._n, 1)[:, None], start)
        with np.errstate(invalid="ignore"):
            turn = rotations.to_rotvec(rotations.multiply(rotations.conjugate(self._reference)[None],
                                                          frames.quaternion))
            mean_turn = np.where(self._n[:, None] > 0, self._turn / np.maximum(self._n, 1)[:, None], 0.0)
            off_position = np.linalg.norm(frames.position - reference, axis=-1)
            off_angle = np.linalg.norm(turn - mean_turn, axis=-1)
        far = valid & ((off_position > self.moved_position) | (off_angle > self.moved_angle))
        moved = np.any(far, axis=1)
        # runs of consecutive moved frames, continuing the run the last batch ended with
        run = np.zeros(len(moved), dtype=int)
        count = self._run
        for i, m in enumerate(moved):  # B is a read's worth of frames; the loop is over frames, not samples
            count = count + 1 if m else 0
            run[i] = count
        hit = np.flatnonzero(run >= self.moved_frames)
        stop = len(frames) if not hit.size else max(int(hit[0]) - self.moved_frames + 1, 1)
        self._run = int(run[stop - 1]) if not hit.size else 0
        use = valid[:stop]
        self._frames += stop
        position = np.where(use[..., None], frames.position[:stop], 0.0)
        turned = np.where(use[..., None], turn[:stop], 0.0)
        self._n += use.sum(axis=0)
        self._sum += position.sum(axis=0)
        self._squares += (position**2).sum(axis=0)
        self._turn += turned.sum(axis=0)
        self._turn_squares += (turned**2).sum(axis=0)
        if not hit.size:
            return None
        distance = off_position[hit[0]][far[hit[0]]]
        angle = off_angle[hit[0]][far[hit[0]]]
        self.last_move = (f"{fixture_name(self.step)} moved during {self._step_words()} "
                          f"({1e3 * np.nanmax(distance):.1f} mm, {1e3 * np.nanmax(angle):.0f} mrad): the step starts "
                          f"again; keep {fixture_name(self.step)} still")
        return stop

    def _step_words(self) -> str:
        return "the survey" if self.step == "cube_survey" else "its calibration" if "calibration" in self.step \
            else self.step

    def standard_errors(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Per sensor: valid frames (N,), the standard error of the mean position (m) and orientation (rad)."""
        if self._n is None:
            return np.zeros(0), np.zeros(0), np.zeros(0)
        n = np.maximum(self._n, 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            var = np.maximum(self._squares / n[:, None] - (self._sum / n[:, None]) ** 2, 0).sum(axis=1)
            turn_var = np.maximum(self._turn_squares / n[:, None] - (self._turn / n[:, None]) ** 2, 0).sum(axis=1)
            correction = n / np.maximum(n - 1, 1)
            se = np.where(self._n > 1, np.sqrt(var * correction / n), np.inf)
            turn_se = np.where(self._n > 1, np.sqrt(turn_var * correction / n), np.inf)
        return self._n.copy(), se, turn_se

    def state(self) -> RuleState:
        n, se, turn_se = self.standard_errors()
        frames = float(self._frames) if self._n is not None else 0.0
        progress = [Progress("frames since still", frames, self.min_frames, "frames"),
                    Progress("position standard error (worst sensor)", 1e3 * float(se.max()) if se.size else np.inf,
                             1e3 * self.position_se, "mm", at_most=True),
                    Progress("orientation standard error (worst sensor)",
                             1e3 * float(turn_se.max()) if turn_se.size else np.inf, 1e3 * self.angle_se, "mrad",
                             at_most=True)]
        problems = []
        if self.restarts:
            problems.append(f"{self.last_move} (restarted {self.restarts} time{'s' if self.restarts > 1 else ''})")
        points = self._sum / np.maximum(self._n, 1)[:, None] if n.size else None
        return RuleState(all(p.done for p in progress), progress, problems, points=points)

    def finish(self) -> None:
        pass

    def usable(self) -> tuple[bool, str]:
        frames = self._frames if self._n is not None else 0
        if frames >= self.min_frames and (self._n > 1).all():
            return True, f"{frames:,} frames since {fixture_name(self.step)} was last still"
        if frames >= self.min_frames:
            return False, f"sensor(s) {np.flatnonzero(self._n < 2).tolist()} have fewer than 2 valid frames"
        return False, (f"only {frames:,} frames since {fixture_name(self.step)} was last still; {self.step} needs "
                       f"{self.min_frames}")


def fibonacci_directions(count: int) -> NDArray[np.float64]:
    """``count`` near-evenly spread unit vectors (count, 3) on the sphere (a Fibonacci lattice)."""
    k = np.arange(count) + 0.5
    z = 1 - 2 * k / count
    phi = np.pi * (1 + 5**0.5) * k
    r = np.sqrt(1 - z**2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def direction_words(direction: NDArray[np.float64]) -> str:
    """A direction (3,) in words: its components of note, e.g. ``+x -z`` (source-frame axes)."""
    parts = [f"{'+' if v > 0 else '-'}{axis}" for axis, v in zip("xyz", direction, strict=True) if abs(v) > 0.35]
    return " ".join(parts) or "+x"


class SweepRule:
    """The wand sweep is done when ``min_kept`` wand samples have passed the fixtures' own gates (sensor 0
    converged inside the cube, its residual and each sample's estimated error; :func:`ivc.fixtures.mapping.map_sweep`
    with the session's calibrations), every octant of the mapped ball holds ``per_octant`` of them in its outer
    half, and each of the :data:`DIRECTION_BINS` cells of the wand's axis directions holds ``per_direction``
    frames whose sensor 0 passed.

    The ball is centred on the placed cube, its radius the wand's longest lever arm plus half the cube's diagonal.
    Without the calibrations (cube_calibration, cube_survey, wand_calibration) in the session, samples cannot be
    gated: valid frames are counted instead and coverage is taken from the reported positions (said so in the
    output). Pose-only sources are gated through the pose path (:func:`ivc.fixtures.reported_mapping.map_sweep_poses`).
    """

    def __init__(self, session: Session, min_kept: int = SWEEP_MIN_KEPT, per_octant: int = SWEEP_PER_OCTANT,
                 per_direction: int = SWEEP_PER_DIRECTION, chunk: int = SWEEP_CHUNK, model=None):
        self.session = session
        self.min_kept, self.per_octant, self.per_direction, self.chunk = int(min_kept), int(per_octant), \
            int(per_direction), int(chunk)
        self.directions = fibonacci_directions(DIRECTION_BINS)
        self.kept = 0
        self.frames = 0
        self.dropped: dict[str, int] = {}
        self.octants = np.zeros(8, dtype=int)
        self.direction_counts = np.zeros(DIRECTION_BINS, dtype=int)
        self.recent_outside = 0.0
        self.recent_rigidity: NDArray[np.float64] | None = None  # (W,) m, each sensor's lever-arm misfit
        self._pending: list[Frames] = []
        self._points = _Reservoir()
        self.model, self.why_ungated = model, None
        self.centre, self.radius, self.axis = None, None, None
        if model is None:
            self._calibrate()
        if self.model is not None:
            self._geometry()
        self.description = (f"wand_sweep: stops when {self.min_kept:,} wand samples pass the fixtures' gates (sensor 0 "
                            f"inside the cube, residual, estimated error), each octant of the mapped ball holds "
                            f"{self.per_octant:,} of them in its outer half, and each of {DIRECTION_BINS} cells of "
                            f"the wand's directions {self.per_direction:,} frames")

    def _calibrate(self) -> None:
        from ivc.fixtures.mapping import FixtureModel
        from ivc.fixtures.measurement import has_signals
        from ivc.fixtures.reported_mapping import PoseFixtureModel

        try:
            if has_signals(self.session, ("cube_survey",)):
                self.model = FixtureModel.from_session(self.session)
            else:
                self.model = PoseFixtureModel.from_session(self.session)
        except IvcError as error:
            self.why_ungated = str(error).splitlines()[0]

    def _geometry(self) -> None:
        wand = self.model.wand
        vertices = self.model.placement.positions if hasattr(self.model, "placement") else self.model.pairs.position
        self.cube = vertices
        self.centre = vertices.mean(axis=0)
        self.radius = float(wand.lever_arms.max() + 0.5 * np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
        far = int(np.argmax(wand.lever_arms))
        self.far = far
        self.axis = wand.positions[far] / max(np.linalg.norm(wand.positions[far]), 1e-12)  # wand frame

    def update(self, frames: Frames) -> int | None:
        self._pending.append(frames)
        if sum(len(f) for f in self._pending) >= self.chunk:
            self._map()
        return None

    def finish(self) -> None:
        if self._pending:
            self._map()

    def _map(self) -> None:
        parts, self._pending = self._pending, []
        frames = Frames(*(np.concatenate([getattr(p, k) for p in parts]) for k in ("time", "valid", "position",
                                                                                    "quaternion")),
                        None if parts[0].signal is None else np.concatenate([p.signal for p in parts]))
        self.frames += len(frames)
        if self.model is None:
            self._ungated(frames)
            return
        self._rigidity(frames)
        positions, rotation0, keep, inside, ok0 = self._gate(frames)
        self.kept += int(keep.sum())
        offset = positions[keep] - self.centre
        outer = np.linalg.norm(offset, axis=1) >= self.radius / 2
        octant = (offset[:, 0] > 0) * 4 + (offset[:, 1] > 0) * 2 + (offset[:, 2] > 0)
        self.octants += np.bincount(octant[outer], minlength=8)
        solved = keep[:, 0]  # the frame's wand pose passed the gates (its far sensor may not have)
        if solved.any():
            direction = rotation0[solved] @ self.axis
            self.direction_counts += np.bincount(np.argmax(direction @ self.directions.T, axis=1),
                                                 minlength=DIRECTION_BINS)
        tried = ok0.sum()
        self.recent_outside = float(np.sum(ok0 & ~inside) / tried) if tried else 0.0
        self._points.add(positions[keep])

    def _rigidity(self, frames: Frames) -> None:
        """Each wand sensor's reported distance from sensor 0 against its calibrated lever arm (median, m)."""
        arms = self.model.wand.lever_arms
        if frames.position.shape[1] != len(arms):
            return
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a sensor invalid over the whole second
            reach = np.linalg.norm(frames.position - frames.position[:, :1], axis=-1)
            self.recent_rigidity = np.nanmedian(np.abs(reach - arms), axis=0)

    def _gate(self, frames: Frames):
        from ivc.fixtures.mapping import FixtureModel, map_sweep
        from ivc.fixtures.reported_mapping import map_sweep_poses

        step = frames.as_step()
        n = step.n_sensors
        if n != len(self.model.wand.positions):
            raise InputError(f"wand_sweep: the source sends {n} sensors but the wand calibration has "
                             f"{len(self.model.wand.positions)}; pass sensors= naming the wand's sensors")
        session = Session(self.session.hemisphere, {"wand_sweep": step})
        if isinstance(self.model, FixtureModel):
            if step.signal is None:  # a pose-only sweep after signal calibrations: rebuild the signals
                step.signal = step.signal_matrices()
            mapping = map_sweep(session, self.model)
            ok0 = step.valid_mask[:, 0] & mapping.sensor0.converged
            rotation0 = mapping.rotations[:, 0]
        else:
            step.signal = None
            mapping = map_sweep_poses(session, self.model)
            ok0 = step.valid_mask[:, 0] & mapping.sensor0.converged
            rotation0 = mapping.rotations[:, 0]
        for reason, count in mapping.dropped.items():
            self.dropped[reason] = self.dropped.get(reason, 0) + count
        return mapping.positions, rotation0, mapping.keep, mapping.inside, ok0

    def _ungated(self, frames: Frames) -> None:
        valid = frames.valid & np.all(np.isfinite(frames.position), axis=-1)
        self.kept += int(valid.sum())
        if self.centre is None and valid[:, 0].any():
            self.centre = np.median(frames.position[valid[:, 0], 0], axis=0)
            reach = np.linalg.norm(frames.position[valid[:, 0]] - frames.position[valid[:, 0], :1], axis=-1)
            self.radius = float(np.nanmax(reach)) + 0.036
        if self.centre is None:
            return
        offset = frames.position[valid] - self.centre
        outer = np.linalg.norm(offset, axis=1) >= self.radius / 2
        octant = (offset[:, 0] > 0) * 4 + (offset[:, 1] > 0) * 2 + (offset[:, 2] > 0)
        self.octants += np.bincount(octant[outer], minlength=8)
        ends = valid[:, 0] & valid[:, -1]
        if ends.any():
            axis = frames.position[ends, -1] - frames.position[ends, 0]
            axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
            self.direction_counts += np.bincount(np.argmax(axis @ self.directions.T, axis=1), minlength=DIRECTION_BINS)
        self._points.add(frames.position[valid])

    def state(self) -> RuleState:
        covered = int(np.sum(self.direction_counts >= self.per_direction))
        progress = [Progress("samples passing the gates" if self.model is not None else "valid samples (ungated)",
                             self.kept, self.min_kept, "samples"),
                    Progress("octants of the ball covered", int(np.sum(self.octants >= self.per_octant)), 8,
                             "octants"),
                    Progress("wand directions covered", covered, DIRECTION_BINS, "cells")]
        problems = []
        if self.model is None and self.why_ungated:
            problems.append(f"the sweep's samples cannot be gated yet ({self.why_ungated}); counting valid samples")
        if self.recent_rigidity is not None and np.nanmax(self.recent_rigidity, initial=0.0) > RIGIDITY_TOLERANCE:
            loose = np.flatnonzero(self.recent_rigidity > RIGIDITY_TOLERANCE)
            problems.append(f"wand sensor{'s' if len(loose) > 1 else ''} {', '.join(map(str, loose))} "
                            f"{'are' if len(loose) > 1 else 'is'} up to {1e3 * np.nanmax(self.recent_rigidity):.0f} mm "
                            "off the wand calibration's lever arms: a loose sensor, or the sensors in the wrong order "
                            "(sensors=)")
        if self.recent_outside > 0.5:
            problems.append(f"sensor 0 left the cube ({100 * self.recent_outside:.0f} % of the last second's frames): "
                            "keep the wand's tip inside the cube")
        thin, target = None, None
        if self.centre is not None:
            octant_share = self.octants / max(self.per_octant, 1) + (self.per_octant <= 0)
            direction_share = self.direction_counts / max(self.per_direction, 1) + (self.per_direction <= 0)
            if octant_share.min() < 1:  # a region of the ball first; then the directions within it
                o = int(np.argmin(octant_share))
                thin = f"the {OCTANT_NAMES[o]} octant of the ball ({self.octants[o]:,} of {self.per_octant:,})"
                sign = np.array([1 if o & 4 else -1, 1 if o & 2 else -1, 1 if o & 1 else -1]) / np.sqrt(3)
                target = self.centre + 0.75 * self.radius * sign
            elif direction_share.min() < 1:
                d = int(np.argmin(direction_share))
                thin = (f"the wand pointing {direction_words(self.directions[d])} "
                        f"({self.direction_counts[d]:,} of {self.per_direction:,} frames)")
                target = self.centre + 0.75 * self.radius * self.directions[d]
        done = all(p.done for p in progress)
        cells = []
        if self.centre is not None:
            for o in range(8):
                sign = np.array([1 if o & 4 else -1, 1 if o & 2 else -1, 1 if o & 1 else -1]) / np.sqrt(3)
                cells.append((self.centre + 0.75 * self.radius * sign, min(self.octants[o] / max(self.per_octant, 1),
                                                                            1.0)))
        return RuleState(done, progress, problems, thin, target, self._points.points.copy(), cells)

    def usable(self) -> tuple[bool, str]:
        if self.kept >= SWEEP_PER_OCTANT:
            return True, f"{self.kept:,} samples passed the gates (the stop rule's coverage may not be reached)"
        return False, f"only {self.kept:,} samples passed the gates"


class ExtensionRule:
    """An extension sweep is done when the wand's sensors have come within ``reach`` m of ``share`` of the
    lattice (``lattice`` m) filling the declared working volume, and of ``face_share`` of each face's 5 cm layer.
    Without a declared working volume (session attributes working_volume_center, working_volume_size) the share
    cannot be stated: the rule then never finishes by itself (give a frame count or a duration, or stop it)."""

    def __init__(self, session: Session, share: float = EXTENSION_SHARE, face_share: float = EXTENSION_FACE_SHARE,
                 lattice: float = EXTENSION_STEP, reach: float = EXTENSION_REACH):
        from scipy.spatial import cKDTree

        self.share, self.face_share, self.reach = float(share), float(face_share), float(reach)
        self.box = working_volume(session.attrs)
        self.frames = 0
        self._points = _Reservoir()
        if self.box is not None:
            self.lattice = box_points(*self.box, lattice)
            self.tree = cKDTree(self.lattice)
            self.covered = np.zeros(len(self.lattice), dtype=bool)
            size = " x ".join(f"{1e3 * s:.0f}" for s in self.box[1])
            self.description = (f"extension sweep: stops when the wand has come within {1e3 * self.reach:.0f} mm of "
                                f"{100 * self.share:.0f} % of the declared working volume ({size} mm) and of "
                                f"{100 * self.face_share:.0f} % of each face's 5 cm layer")
        else:
            self.description = ("extension sweep: the session declares no working volume, so its coverage cannot be "
                                "stated; stop it by a frame count, a duration or by hand")

    def update(self, frames: Frames) -> int | None:
        self.frames += len(frames)
        points = frames.position[frames.valid]
        points = points[np.all(np.isfinite(points), axis=1)]
        self._points.add(points)
        if self.box is not None and len(points):
            for near in self.tree.query_ball_point(points[:: max(1, len(points) // 4000)], self.reach):
                self.covered[near] = True
        return None

    def finish(self) -> None:
        pass

    def shares(self) -> tuple[float, dict[str, float]]:
        """The covered share of the working volume and, per face, of its 5 cm layer (0-1)."""
        return float(self.covered.mean()), face_shares(self.lattice, self.covered, *self.box)

    def state(self) -> RuleState:
        if self.box is None:
            return RuleState(False, [Progress("frames", self.frames, np.inf, "frames")],
                             ["no declared working volume: coverage cannot be stated"],
                             points=self._points.points.copy())
        total, faces = self.shares()
        progress = [Progress("working volume covered", 100 * total, 100 * self.share, "%")]
        progress += [Progress(f"face {face} covered", 100 * faces[face], 100 * self.face_share, "%")
                     for face in FACES if np.isfinite(faces[face])]
        thin, target = None, None
        if not all(p.done for p in progress):
            face = min((f for f in FACES if np.isfinite(faces[f])), key=lambda f: faces[f])
            thin = f"face {face} of the working volume ({100 * faces[face]:.0f} % covered)"
            missing = self.lattice[~self.covered]
            if len(missing):
                target = missing[np.argmin(np.linalg.norm(missing - missing.mean(axis=0), axis=1))]
        centre, size = self.box
        cells = [(centre + np.eye(3)[a] * size[a] / 2 * (1 if sign == "+" else -1), faces[f"{sign}{axis}"])
                 for a, axis in enumerate("xyz") for sign in "-+"]
        return RuleState(all(p.done for p in progress), progress, [], thin, target, self._points.points.copy(),
                         cells)

    def usable(self) -> tuple[bool, str]:
        if self.frames >= MIN_KEPT_FRAMES:
            return True, f"{self.frames:,} frames recorded"
        return False, f"only {self.frames} frames recorded; an extension sweep needs at least {MIN_KEPT_FRAMES}"


class CountRule:
    """Done after ``frames`` frames, or ``duration_s`` seconds of the source's clock (one of the two)."""

    def __init__(self, step: str, frames: int | None = None, duration_s: float | None = None):
        if (frames is None) == (duration_s is None):
            raise InputError("a count rule takes a number of frames or a duration, one of the two")
        if frames is not None and frames < 1:
            raise InputError(f"frames must be at least 1, got {frames}")
        if duration_s is not None and not duration_s > 0:
            raise InputError(f"duration_s must be a positive number of seconds, got {duration_s}")
        self.step = step
        self.target_frames, self.duration_s = frames, duration_s
        self.frames = 0
        self.start: float | None = None
        self.elapsed = 0.0
        self._points = _Reservoir()
        self.description = (f"{step}: stops after {frames:,} frames" if frames is not None
                            else f"{step}: stops after {duration_s:g} s of tracker time")

    def update(self, frames: Frames) -> int | None:
        if not len(frames):
            return None
        if self.start is None:
            self.start = float(frames.time[0])
        self.frames += len(frames)
        self.elapsed = float(frames.time[-1]) - self.start
        self._points.add(frames.position[frames.valid])
        return None

    def finish(self) -> None:
        pass

    def state(self) -> RuleState:
        if self.target_frames is not None:
            progress = Progress("frames", self.frames, self.target_frames, "frames")
        else:
            progress = Progress("tracker time", self.elapsed, self.duration_s, "s")
        return RuleState(progress.done, [progress], points=self._points.points.copy())

    def usable(self) -> tuple[bool, str]:
        minimum = 1 if self.step == "check" else MIN_FRAMES.get(self.step, MIN_KEPT_FRAMES)
        if self.frames >= minimum:
            return True, f"{self.frames:,} frames recorded"
        return False, f"only {self.frames} frames recorded; {self.step} needs at least {minimum}"


def default_rule(step: str, session: Session, frames: int | None = None,
                 duration_s: float | None = None) -> StopRule:
    """The stop rule of ``step``: a count of ``frames`` or ``duration_s`` when one is given, else the step's own
    (static steps: :class:`StaticRule`; wand_sweep: :class:`SweepRule` with ``session``'s calibrations;
    extension sweeps: :class:`ExtensionRule`; check: :data:`CHECK_FRAMES` frames)."""
    if frames is not None or duration_s is not None:
        return CountRule(step, frames, duration_s)
    if step in STATIC_STEPS:
        return StaticRule(step)
    if step == "wand_sweep":
        return SweepRule(session)
    if is_extension_step(step):
        return ExtensionRule(session)
    if step == "check":
        return CountRule(step, CHECK_FRAMES)
    raise InputError(f"no stop rule for step {step!r}")
