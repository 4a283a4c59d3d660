"""Simulated fixtures (their true, imperfect geometry) and how they move.

Body frames: the cube's body origin is its nominal vertex 0, with nominal vertex ``n``
at ``edge · (x, y, z)`` for ``n = 4x + 2y + z``; the wand's body origin is sensor 0,
with sensor ``n`` nominally at ``n · spacing`` along body x. A sensor's pose in the
source frame is ``p + R b_n`` and ``R T_n``, for a body pose ``(p, R)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ivc import rotations
from ivc.fixtures.cube import CUBE_BITS
from ivc.fixtures.geometry import FixtureGeometry
from ivc.sim.scene import CubeSpec, Scene, WandSpec


@dataclass
class RigidFixture:
    """Sensors rigidly mounted on a body: positions (N, 3) m and orientations (N, 4) in the body frame."""

    body_positions: np.ndarray
    body_quaternions: np.ndarray

    def sensor_poses(self, position: np.ndarray, quaternion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sensor poses (F, N, 3), (F, N, 4) for body poses ``position`` (F, 3), ``quaternion`` (F, 4)."""
        position = np.atleast_2d(position)
        quaternion = np.atleast_2d(quaternion)
        R = rotations.to_matrix(quaternion)
        positions = position[:, None, :] + np.einsum("fij,nj->fni", R, self.body_positions)
        quaternions = rotations.canonical(rotations.multiply(quaternion[:, None, :], self.body_quaternions[None]))
        return positions, quaternions


#: a correct print's errors, 1 sigma per axis: a sensor's position (m; an FDM printer's 0.2-0.3 mm and the
#: pocket's clearance) and orientation (rad) in its pocket (docs/printing.md)
PRINT_POSITION_SIGMA = 0.1e-3
PRINT_ANGLE_SIGMA = float(np.radians(0.25))


def build_fixture(geometry: FixtureGeometry, rng: np.random.Generator, *, origin: np.ndarray | None = None,
                  position_sigma: float = PRINT_POSITION_SIGMA, angle_sigma: float = PRINT_ANGLE_SIGMA,
                  swaps: tuple[tuple[int, int], ...] = (), turns: dict[int, np.ndarray] | None = None,
                  lifts: dict[int, np.ndarray] | None = None) -> RigidFixture:
    """A fixture printed from ``geometry`` and assembled, with a correct print's random errors and build faults.

    The body frame has the part frame's axes and its origin at ``origin`` (part frame, m; default the part
    frame's own). Faults: ``swaps`` (pairs of sensors that sit in each other's pockets), ``turns`` (sensor
    -> rotation vector, rad, in the sensor's own axes), ``lifts`` (sensor -> offset, m, part frame).
    """
    n = geometry.n_sensors
    positions = geometry.positions - (np.zeros(3) if origin is None else np.asarray(origin, float))
    positions = positions + position_sigma * rng.standard_normal((n, 3))
    errors = rotations.from_rotvec(angle_sigma * rng.standard_normal((n, 3)))
    quaternions = rotations.multiply(geometry.quaternions, errors)
    for a, b in swaps:
        positions[[a, b]] = positions[[b, a]]
        quaternions[[a, b]] = quaternions[[b, a]]
    for k, turn in (turns or {}).items():
        quaternions[k] = rotations.multiply(quaternions[k], rotations.from_rotvec(np.asarray(turn, float)))
    for k, lift in (lifts or {}).items():
        positions[k] = positions[k] + np.asarray(lift, float)
    return RigidFixture(positions, rotations.canonical(quaternions))


def random_build(geometry: FixtureGeometry, rng: np.random.Generator, *, origin: np.ndarray | None = None,
                 fault_probability: float = 0.5) -> tuple[RigidFixture, dict]:
    """A random build of ``geometry`` for testing the build check: with probability ``1 − fault_probability``
    a correct print (:func:`build_fixture`'s errors only); else each of these faults with probability 1/2
    (at least one), on distinct sensors: two sensors swapped, a sensor turned by 2-90° about a random axis,
    a sensor moved by 1-4 mm in a random direction. Returns the fixture and its faults (``build_fixture``'s
    keyword arguments)."""
    n = geometry.n_sensors
    faults: dict = {"swaps": (), "turns": {}, "lifts": {}}
    if rng.random() < fault_probability:
        chosen = [False, False, False]
        while not any(chosen):
            chosen = list(rng.random(3) < 0.5)
        order = rng.permutation(n)
        if chosen[0]:
            faults["swaps"] = ((int(order[0]), int(order[1])),)
        if chosen[1]:
            axis = rng.standard_normal(3)
            faults["turns"] = {int(order[2]): np.radians(rng.uniform(2, 90)) * axis / np.linalg.norm(axis)}
        if chosen[2]:
            direction = rng.standard_normal(3)
            faults["lifts"] = {int(order[3]): rng.uniform(1e-3, 4e-3) * direction / np.linalg.norm(direction)}
    return build_fixture(geometry, rng, origin=origin, **faults), faults


def build_deviations(geometry: FixtureGeometry, fixture: RigidFixture, origin: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """How far each built sensor sits from its own pocket's nominal pose: position (N,) m and angle (N,) rad
    (for a 5-DOF sensor, of its measured axis). ``origin``: as for :func:`build_fixture`."""
    shift = np.zeros(3) if origin is None else np.asarray(origin, float)
    position = np.linalg.norm(fixture.body_positions + shift - geometry.positions, axis=1)
    if geometry.sensor.dof == 5:
        k = geometry.sensor.axis
        built = rotations.to_matrix(fixture.body_quaternions)[:, :, k]
        cos = np.einsum("ni,ni->n", built, geometry.matrices[:, :, k])
        return position, np.arccos(np.clip(cos, -1.0, 1.0))
    return position, rotations.angle_between(fixture.body_quaternions, geometry.quaternions)


def geometry_body_pose(geometry: FixtureGeometry, spec: CubeSpec) -> tuple[np.ndarray, np.ndarray]:
    """Part-frame pose that puts the printed cube's nominal sensor centroid at ``spec.center``, turned by
    ``spec.quaternion``: where the simulator places a cube built from ``geometry``."""
    R = rotations.to_matrix(spec.quaternion)
    return spec.center - R @ geometry.positions.mean(axis=0), spec.quaternion.copy()


def make_cube(spec: CubeSpec, rng: np.random.Generator) -> RigidFixture:
    """An interpolation cube whose sensors sit ``mounting_sigma`` off the vertices, randomly oriented."""
    positions = spec.edge * CUBE_BITS + spec.mounting_sigma * rng.standard_normal((8, 3))
    return RigidFixture(positions, rotations.random(8, rng))


def make_wand(spec: WandSpec, rng: np.random.Generator) -> RigidFixture:
    """A mapping wand: sensors ``spacing`` apart along body x with small lateral offsets."""
    n = np.arange(spec.sensors)
    positions = np.zeros((spec.sensors, 3))
    positions[:, 0] = n * spec.spacing
    positions[1:, 1:] = spec.lateral_sigma * rng.standard_normal((spec.sensors - 1, 2))
    return RigidFixture(positions, rotations.random(spec.sensors, rng))


def cube_body_pose(spec: CubeSpec) -> tuple[np.ndarray, np.ndarray]:
    """Body pose (origin at nominal vertex 0) that puts the nominal cube centre at ``spec.center``."""
    R = rotations.to_matrix(spec.quaternion)
    return spec.center - R @ np.full(3, spec.edge / 2), spec.quaternion.copy()


def _smooth_offsets(times: np.ndarray, amplitude: float, rng: np.random.Generator, components: int = 3):
    """A smooth bounded wander, |x_i| <= amplitude: sums of slow sinusoids with random phases."""
    frequencies = rng.uniform(0.02, 0.15, (components, 3))
    phases = rng.uniform(0, 2 * np.pi, (components, 3))
    weights = rng.uniform(0.5, 1.0, (components, 3))
    weights /= weights.sum(axis=0)
    waves = np.sin(2 * np.pi * frequencies[None] * times[:, None, None] + phases[None])
    return amplitude * np.einsum("fci,ci->fi", waves, weights)


def _prefix_product(steps: np.ndarray) -> np.ndarray:
    """q_k = steps_k ⊗ ... ⊗ steps_0 for all k, by a log-depth parallel scan (no loop over frames)."""
    q = steps.copy()
    shift = 1
    while shift < len(q):
        q[shift:] = rotations.multiply(q[shift:], q[:-shift])
        q[shift:] /= np.linalg.norm(q[shift:], axis=1, keepdims=True)
        shift *= 2
    return q


def spiral_directions(frames: int, rate_hz: float, angular_speed: float) -> np.ndarray:
    """Unit directions (F, 3) along a spherical spiral that covers the sphere evenly at ~constant speed.

    The spiral is ``φ = k θ`` about source z; ``k`` is chosen so that the path, walked
    at ``angular_speed`` rad/s, takes the sweep's duration. Turns are then 2π/k apart.
    """
    duration = frames / rate_hz
    k = max(angular_speed * duration / 2.0, 1.0)
    theta_grid = np.linspace(0.0, np.pi, 20_001)
    speed_factor = np.sqrt(1.0 + (k * np.sin(theta_grid)) ** 2)  # ds/dθ
    arc = np.concatenate([[0.0], np.cumsum(0.5 * (speed_factor[1:] + speed_factor[:-1]) * np.diff(theta_grid))])
    s = np.linspace(0.0, arc[-1], frames)
    theta = np.interp(s, arc, theta_grid)
    phi = k * theta
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)


def _transported(directions: np.ndarray, times: np.ndarray, rate_hz: float, roll_phase: float,
                 start_roll: float) -> np.ndarray:
    """Orientations (F, 4) whose body x follows ``directions`` (F, 3) by parallel transport (the minimal
    rotation from each direction to the next), with a slow extra roll about it (``0.1 sin(2π t/40 s +
    roll_phase)`` rad/s) and the first frame rolled by ``start_roll``; built by a prefix product."""
    axis = np.cross(directions[:-1], directions[1:])
    angle = np.arctan2(np.linalg.norm(axis, axis=1), np.einsum("ij,ij->i", directions[:-1], directions[1:]))
    norm = np.linalg.norm(axis, axis=1, keepdims=True)
    transport = rotations.from_rotvec(np.where(norm > 0, axis / np.maximum(norm, 1e-300), 0.0) * angle[:, None])
    roll_rate = 0.1 * np.sin(2 * np.pi * times[1:] / 40.0 + roll_phase)  # rad/s
    roll = rotations.from_rotvec(directions[1:] * (roll_rate / rate_hz)[:, None])
    # initial orientation: body x along the first direction, rolled by start_roll
    x = directions[0]
    helper = np.array([0.0, 0.0, 1.0]) if abs(x[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    y = np.cross(helper, x)
    y /= np.linalg.norm(y)
    start = rotations.from_matrix(np.stack([x, y, np.cross(x, y)], axis=1))
    start = rotations.multiply(rotations.from_rotvec(x * start_roll), start)
    steps = np.concatenate([start[None], rotations.multiply(roll, transport)])
    return rotations.canonical(_prefix_product(steps))


def sweep_motion(scene: Scene, frames: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Wand body poses for the sweep: sensor 0 wanders inside the cube, the wand's axis covers the sphere.

    The orientation is the parallel transport of the wand axis along the spiral (angular
    speed ``scene.sweep_angular_speed``) with a slow extra roll about the axis, built
    by a prefix product of per-frame rotations.
    """
    times = np.arange(frames) / scene.sweep_rate_hz
    directions = spiral_directions(frames, scene.sweep_rate_hz, scene.sweep_angular_speed)
    roll_phase = rng.uniform(0, 2 * np.pi)
    quaternions = _transported(directions, times, scene.sweep_rate_hz, roll_phase, rng.uniform(0, 2 * np.pi))
    # sensor 0 stays well inside the cube (mounting errors are a few % of the edge)
    amplitude = 0.3 * scene.cube.edge
    cube_rotation = rotations.to_matrix(scene.cube.quaternion)
    positions = scene.cube.center + _smooth_offsets(times, amplitude, rng) @ cube_rotation.T
    return positions, quaternions


#: the hand keeps this far inside the working volume's faces (m)
HAND_MARGIN = 0.03


#: in the "passes" pattern the hand's outermost passes run this far inside the volume's faces (m; negative:
#: beyond them): the map's cells must reach the faces with data on both sides, and the metal of a cockpit is
#: several centimetres beyond them
PASS_MARGIN = -0.02
#: the nested boxes the hand walks in the "passes" pattern: fractions of the way from the cube to the volume
SHELLS = (0.5, 0.75, 1.0)
#: in the "passes" pattern the hand keeps at least this far from the cube's centre (m): nearer, the wand
#: would point through the cube, and the cube sweep has mapped that region already
HAND_MIN_RADIUS = 0.25


def _rectangle(centre: np.ndarray, a: float, b: float, z: float) -> np.ndarray:
    """The corners (5, 3) of one loop round the horizontal rectangle of half-sides (a, b), closed."""
    corners = np.array([[-a, -b], [a, -b], [a, b], [-a, b], [-a, -b]])
    return np.column_stack([centre[0] + corners[:, 0], centre[1] + corners[:, 1], np.full(5, z)])


def shell_passes(low: np.ndarray, high: np.ndarray, pitch: float) -> np.ndarray:
    """Waypoints (P, 3) of passes over the whole surface of the box ``[low, high]``, at most ``pitch`` m
    apart, in one continuous walk that never crosses the box's inside: loops growing from the middle of
    the bottom face to its edge, a helix up the four side faces, loops shrinking to the middle of the top."""
    centre, half = (low + high) / 2, (high - low) / 2
    rings = max(int(np.ceil(max(half[0], half[1]) / pitch - 1e-9)), 1)
    grow = [_rectangle(centre, half[0] * k / rings, half[1] * k / rings, low[2]) for k in range(rings + 1)]
    turns = max(int(np.ceil((high[2] - low[2]) / pitch - 1e-9)), 1)
    helix = np.concatenate([_rectangle(centre, half[0], half[1], 0.0)[:-1]] * turns + [[[0, 0, 0.0]]])
    helix[-1, :2] = helix[0, :2]
    perimeter = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(helix[:, :2], axis=0), axis=1))])
    helix[:, 2] = low[2] + (high[2] - low[2]) * perimeter / perimeter[-1]
    shrink = [_rectangle(centre, half[0] * k / rings, half[1] * k / rings, high[2]) for k in range(rings, -1, -1)]
    return np.concatenate([*grow, helix, *shrink])


def _polyline_length(points: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1)))


def pass_pattern(scene: Scene, pitch: float) -> np.ndarray:
    """Waypoints (P, 3) of the "passes" pattern: :func:`shell_passes` over nested boxes, from the cube's
    centre towards the volume shrunk by :data:`PASS_MARGIN` at the fractions :data:`SHELLS`, inner first;
    every other box walked backwards, so that each ends where the next begins (the middle of a top or a
    bottom face) and the hand never crosses the cube."""
    volume, centre = scene.volume, np.asarray(scene.cube.center, float)
    low, high = volume.lower + PASS_MARGIN, volume.upper - PASS_MARGIN
    shells = [shell_passes(centre + f * (low - centre), centre + f * (high - centre), pitch) for f in SHELLS]
    return np.concatenate([walk[::-1] if k % 2 else walk for k, walk in enumerate(shells)])


def pass_pitch(scene: Scene) -> float:
    """The passes' pitch (m) at which the whole pattern is as long as the scene's sweeps can walk at its
    speed (``sweeps · frames / rate · speed``); the path length is area / pitch plus the turns."""
    spec = scene.extension
    target = spec.speed * max(spec.sweeps, 1) * spec.frames / scene.sweep_rate_hz
    p1, p2 = 0.05, 0.1
    l1, l2 = _polyline_length(pass_pattern(scene, p1)), _polyline_length(pass_pattern(scene, p2))
    area = (l1 - l2) / (1 / p1 - 1 / p2)
    rest = l1 - area / p1
    return float(np.clip(area / max(target - rest, 1e-9), 0.01, 0.3))


def _hand_on_passes(scene: Scene, frames: int, sweep: int) -> np.ndarray:
    """The hand (F, 3) of extension sweep ``sweep`` (1-based) in the "passes" pattern: the sweeps walk
    successive equal shares of one pattern (sweep N + 1 walks the first share again), at constant speed."""
    spec, volume = scene.extension, scene.volume
    waypoints = pass_pattern(scene, pass_pitch(scene))
    length = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(waypoints, axis=0), axis=1))])
    count = max(spec.sweeps, 1)
    share = (sweep - 1) % count
    s = (share + (np.arange(frames) + 0.5) / frames) / count * length[-1]
    hand = np.stack([np.interp(s, length, waypoints[:, a]) for a in range(3)], axis=1)
    centre = np.asarray(scene.cube.center, float)
    offset = hand - centre
    radius = np.linalg.norm(offset, axis=1, keepdims=True)
    hand = centre + offset / np.maximum(radius, 1e-9) * np.maximum(radius, HAND_MIN_RADIUS)
    return np.clip(hand, volume.lower + PASS_MARGIN, volume.upper - PASS_MARGIN)


def _hand_on_lissajous(scene: Scene, times: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    volume, spec = scene.volume, scene.extension
    amplitude = np.maximum(volume.size / 2 - HAND_MARGIN, 0.01)
    ratios = np.array([1.0, 0.79, 0.61]) * rng.uniform(0.9, 1.1, 3)
    frequency = spec.speed / (2 * np.pi * amplitude) * ratios / np.sqrt(np.sum(ratios**2) / 2)
    phase = rng.uniform(0, 2 * np.pi, 3)
    return volume.center + amplitude * np.sin(2 * np.pi * frequency * times[:, None] + phase)


def extension_motion(scene: Scene, frames: int, rng: np.random.Generator,
                     sweep: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Wand body poses of extension sweep ``sweep`` (1-based): a person walks the wand, held at its far end
    (the last sensor), through the working volume in passes, its tip (sensor 0) pointing back towards the cube.

    The hand's path is ``scene.extension.pattern``, at about ``scene.extension.speed`` m/s, at least
    :data:`PASS_MARGIN` (passes) or :data:`HAND_MARGIN` (Lissajous) inside the volume's faces:

    - ``"passes"``: passes over the whole surface of nested boxes between the cube and the volume
      (:func:`pass_pattern`, inner boxes first, so the far end always reaches a little beyond what the
      tip's end already covers), their pitch set so that the scene's sweeps walk the whole pattern
      (:func:`pass_pitch`); the sweeps walk successive shares of it. Every corner of the volume is visited.
    - ``"lissajous"``: a Lissajous path over the volume (incommensurate frequencies and random phases
      per sweep, so successive passes cross the box at new places).

    The tip points at the cube's centre plus a smooth wander (within ``wobble_deg`` of the cube's
    direction seen from 0.3 m), so some sensors stay near the region mapped from the cube while the hand
    is far out; the wand rolls slowly about its axis. The body origin is sensor 0 and body x runs from the
    tip to the hand (``ivc.sim.rig`` frames).
    """
    volume, spec = scene.volume, scene.extension
    if volume is None:
        raise ValueError("extension sweeps need the scene's working volume")
    times = np.arange(frames) / scene.sweep_rate_hz
    if spec.pattern == "lissajous":
        hand = _hand_on_lissajous(scene, times, rng)
    else:
        hand = _hand_on_passes(scene, frames, sweep)
    wobble = np.tan(np.radians(spec.wobble_deg)) * 0.3
    target = scene.cube.center + _smooth_offsets(times, wobble, rng) * np.array([1.0, 1.0, 1.0])
    target = np.clip(target, volume.lower + HAND_MARGIN, volume.upper - HAND_MARGIN)
    tip_direction = target - hand
    tip_direction /= np.maximum(np.linalg.norm(tip_direction, axis=1, keepdims=True), 1e-9)
    length = (scene.wand.sensors - 1) * scene.wand.spacing
    quaternions = _transported(-tip_direction, times, scene.sweep_rate_hz, rng.uniform(0, 2 * np.pi),
                               rng.uniform(0, 2 * np.pi))
    return hand + length * tip_direction, quaternions


def check_poses(scene: Scene, frames: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Independent random poses (F, 1, 3), (F, 1, 4): positions uniform in the mapped ball (uniform in the
    scene's working volume when it has one), any orientation."""
    if scene.volume is not None:
        positions = scene.volume.lower + scene.volume.size * rng.random((frames, 3))
        return positions[:, None, :], rotations.random((frames, 1), rng)
    direction = rng.standard_normal((frames, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = scene.check_radius * rng.random(frames) ** (1 / 3)
    positions = scene.cube.center + direction * radius[:, None]
    return positions[:, None, :], rotations.random((frames, 1), rng)
