"""Simulate the six-step protocol (Himberg 2010, ch. 4.4.3) in a scene, step by step.

A :class:`Simulator` is fixed by its scene and seed: the fixtures' true geometry, the
cube's placement error and each step's noise come from separate random streams, so a
step simulated alone equals the same step simulated within the whole protocol, and
the same seed always gives the same session.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from functools import cached_property

import numpy as np

from ivc import rotations
from ivc.dipole.tracker import Tracker
from ivc.errors import InputError
from ivc.fixtures import fixture_frame
from ivc.fixtures.geometry import FixtureGeometry
from ivc.session import STEPS, Session, Step, Truth, describe_step, extension_step, is_extension_step, step_order
from ivc.sim import rig
from ivc.sim.field import SecondaryField
from ivc.sim.scene import Scene
from ivc.sim.tracker import SimulatedTracker

DEFAULT_FRAMES = {
    "cube_calibration": 2000,
    "cube_survey": 500,
    "wand_calibration": 500,
    "wand_sweep": 100_000,
    "check": 10_000,
}
_STREAMS = {
    "cube": 1, "wand": 2, "placement": 3, "cube_calibration": 10, "cube_survey": 11,
    "wand_calibration": 12, "wand_sweep": 13, "check": 14,
}
#: random stream of extension sweep n: EXTENSION_STREAM + n
EXTENSION_STREAM = 100


#: the largest seed: the session file stores it as a 64-bit signed integer attribute
MAX_SEED = 2**63 - 1


def _checked_seed(seed) -> int:
    """``seed`` as an int in 0..MAX_SEED, or an InputError before any work (NumPy refuses negative seeds only
    when the first random stream is made, and HDF5 cannot store one above 2**63 - 1 when the session is written)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise InputError(f"seed must be a whole number from 0 to {MAX_SEED}, got {seed!r}")
    if not 0 <= int(seed) <= MAX_SEED:
        raise InputError(f"seed must be from 0 to {MAX_SEED} (2**63 - 1), got {int(seed)}")
    return int(seed)


class Simulator:
    """A simulated tracker, fixtures and room for one scene and seed; ``tracker``: an imperfect device."""

    def __init__(self, scene: Scene, seed: int = 0, tracker: Tracker | None = None, *,
                 cube_geometry: FixtureGeometry | None = None, wand_geometry: FixtureGeometry | None = None):
        """``cube_geometry``, ``wand_geometry``: fixtures printed from geometry files (docs/printing.md) in place
        of the scene's hand-built ones; the cube's declared pose then comes from its file. ``cube`` and
        ``wand`` are attributes: replace one (``rig.build_fixture``) to simulate a faulty build."""
        self.scene = scene
        self.seed = _checked_seed(seed)
        self.tracker = tracker  # the device's own coil model (None: ideal)
        for geometry, kind in ((cube_geometry, "cube"), (wand_geometry, "wand")):
            if geometry is not None and geometry.kind != kind:
                raise InputError(f"the {kind}'s geometry file describes a {geometry.kind}")
        self.cube_geometry, self.wand_geometry = cube_geometry, wand_geometry
        self.cube = (rig.make_cube(scene.cube, self._rng("cube")) if cube_geometry is None
                     else rig.build_fixture(cube_geometry, self._rng("cube")))
        self.wand = (rig.make_wand(scene.wand, self._rng("wand")) if wand_geometry is None
                     else rig.build_fixture(wand_geometry, self._rng("wand"), origin=wand_geometry.positions[0]))

    def _rng(self, purpose: str) -> np.random.Generator:
        if is_extension_step(purpose):
            return np.random.default_rng([self.seed, EXTENSION_STREAM + int(purpose.rsplit("_", 1)[1])])
        return np.random.default_rng([self.seed, _STREAMS[purpose]])

    @property
    def extension_steps(self) -> list[str]:
        """The scene's extension sweeps (``extension_sweep_1`` …), recorded after the wand sweep."""
        return [extension_step(n + 1) for n in range(self.scene.extension.sweeps)]

    @property
    def steps(self) -> list[str]:
        """Every step this scene's protocol records, in recording order."""
        return sorted([*STEPS, *self.extension_steps], key=step_order)

    @property
    def device(self) -> SimulatedTracker:
        """The simulated tracker that records each step: the scene's noise, rate, hemisphere and solver, and the
        device's coil model."""
        scene = self.scene
        return SimulatedTracker(scene.noise, scene.sweep_rate_hz, scene.hemisphere, scene.solver, self.tracker)

    @cached_property
    def secondary(self) -> SecondaryField:
        """The scene's secondary field, solved on first use."""
        return self.scene.secondary_field()

    def prepare(self, progress: Callable[[int, int], None] | None = None) -> SecondaryField:
        """Solve the scene's eddy currents and tabulate their field now rather than at the first distorted step.

        ``progress(done, total)`` follows the tabulation, slab by slab. Returns the field.
        """
        field = self.secondary
        field.tabulate(progress=progress)
        return field

    def cube_body_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The cube's body pose during the survey (a printed cube's: its part frame's)."""
        if self.cube_geometry is not None:
            return rig.geometry_body_pose(self.cube_geometry, self.scene.cube)
        return rig.cube_body_pose(self.scene.cube)

    def true_cube_frame(self) -> tuple[np.ndarray, np.ndarray]:
        """True pose ``(r_0, T_I)`` of the cube fixture frame (docs/math.md §5) during the survey."""
        body_position, body_quaternion = self.cube_body_pose()
        origin, T_body = fixture_frame(self.cube.body_positions)
        R = rotations.to_matrix(body_quaternion)
        return body_position + R @ origin, R @ T_body

    def declared_cube_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The user's declared cube pose: the true one with a realistic placement error.

        A printed cube's is its geometry file's declared frame, carried by the part's placement (the
        true part pose with the placement error): no sensor is measured for it.
        Returns ``(declared_position (3,), declared_quaternion (4,))``.
        """
        rng = self._rng("placement")
        offset = self.scene.cube.placement_sigma * rng.standard_normal(3)
        tilt = rotations.from_rotvec(self.scene.cube.placement_sigma_rad * rng.standard_normal(3))
        if self.cube_geometry is not None:
            part_position, part_quaternion = self.cube_body_pose()
            return self.cube_geometry.declared_pose(part_position + offset, rotations.multiply(tilt, part_quaternion))
        r0, T_I = self.true_cube_frame()
        return r0 + offset, rotations.canonical(rotations.multiply(tilt, rotations.from_matrix(T_I)))

    def step(self, name: str, frames: int | None = None) -> tuple[Step, Truth]:
        """Simulate one protocol step; returns the recorded step and its truth."""
        extension = is_extension_step(name)
        if name not in DEFAULT_FRAMES and not extension:
            raise InputError(f"unknown step {name!r}; the steps are {', '.join(DEFAULT_FRAMES)} and extension_sweep_N")
        if extension and self.scene.volume is None:
            raise InputError(f"{name}: scene {self.scene.name!r} has no working volume ([volume]) to walk the wand "
                             "through")
        default = self.scene.extension.frames if extension else DEFAULT_FRAMES[name]
        frames = default if frames is None else int(frames)
        if frames < 1:
            raise InputError(f"{name}: frames must be at least 1, got {frames}")
        rng = self._rng(name)
        scene = self.scene
        attrs = {}
        if name == "cube_calibration":
            body = (np.asarray(scene.cube.center), rotations.random(1, rng)[0])
            positions, quaternions = self._static(self.cube, *body, frames)
        elif name == "cube_survey":
            positions, quaternions = self._static(self.cube, *self.cube_body_pose(), frames)
            declared_position, declared_quaternion = self.declared_cube_pose()
            attrs = {"declared_position": declared_position, "declared_quaternion": declared_quaternion}
        elif name == "wand_calibration":
            positions, quaternions = self._static(self.wand, scene.cube.center, rotations.random(1, rng)[0], frames)
        elif name == "wand_sweep":
            positions, quaternions = self.wand.sensor_poses(*rig.sweep_motion(scene, frames, rng))
        elif extension:
            positions, quaternions = self.wand.sensor_poses(*rig.extension_motion(scene, frames, rng,
                                                                               int(name.rsplit("_", 1)[1])))
        else:
            positions, quaternions = rig.check_poses(scene, frames, rng)
        distorted = name in ("cube_survey", "wand_sweep", "check") or extension
        step = self.device.measure(
            positions,
            quaternions,
            secondary=self.secondary if distorted else None,
            rng=rng,
            description=f"simulated: {describe_step(name)} (scene {scene.name!r}, seed {self.seed})",
            sensor_prefix="cube" if name.startswith("cube") else (
                "wand" if name.startswith("wand") or extension else "check"),
        )
        step.attrs.update(attrs, tracker_solver=scene.solver)
        return step, Truth(positions, quaternions)

    def protocol(self, frames: Mapping[str, int | None] | None = None, *, steps: Sequence[str] | None = None,
                 on_step: Callable[[str, Step, Session], None] | None = None) -> Session:
        """Simulate the protocol, every step of ``steps`` in recording order, into a new session.

        ``frames`` maps step names to frame counts; a step left out (or ``None``) gets
        its :data:`DEFAULT_FRAMES` (an extension sweep: the scene's ``[extension] frames``).
        ``steps``: a subset of the protocol (default: :attr:`steps`, the five steps and the
        scene's extension sweeps). ``on_step(name, step, session)`` is called after each step is added (for
        progress or checks). The session records the scene's hemisphere and ``attrs``
        ``scene`` and ``seed`` (and the scene's working volume, ``working_volume_center`` and
        ``working_volume_size``, when it has one); every step has its truth. A step equals the same step
        simulated alone with :meth:`step`.
        """
        frames = dict(frames or {})
        steps = self.steps if steps is None else list(steps)
        unknown = sorted(n for n in set(frames) | set(steps) if n not in STEPS and not is_extension_step(n))
        if unknown:
            raise InputError(f"unknown step {', '.join(map(repr, unknown))}; the steps are {', '.join(STEPS)} and "
                             "extension_sweep_N")
        attrs = {"scene": self.scene.name, "seed": self.seed}
        if self.scene.volume is not None:  # the box the user wants mapped (docs/session-format.md)
            attrs.update(working_volume_center=np.asarray(self.scene.volume.center, float),
                         working_volume_size=np.asarray(self.scene.volume.size, float))
        session = Session(hemisphere=self.scene.hemisphere, attrs=attrs)
        for name in sorted(set(steps), key=step_order):
            step, truth = self.step(name, frames.get(name))
            session.steps[name], session.truth[name] = step, truth
            if on_step is not None:
                on_step(name, step, session)
        return session

    @staticmethod
    def _static(fixture: rig.RigidFixture, position, quaternion, frames: int):
        positions, quaternions = fixture.sensor_poses(np.asarray(position)[None], np.asarray(quaternion)[None])
        return np.repeat(positions, frames, axis=0), np.repeat(quaternions, frames, axis=0)
