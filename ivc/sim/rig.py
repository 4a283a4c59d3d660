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


def extension_motion(scene: Scene, frames: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Wand body poses of one extension sweep: a person walks the wand, held at its far end (the last
    sensor), through the working volume in passes, its tip (sensor 0) pointing back towards the cube.

    The hand follows a Lissajous path over the volume shrunk by :data:`HAND_MARGIN` (incommensurate
    frequencies and random phases per sweep, so successive passes cross the box at new places) at
    about ``scene.extension.speed`` m/s. The tip points at the cube's centre plus a smooth wander
    (within ``wobble_deg`` of the cube's direction seen from 0.3 m), so some sensors stay near the
    region mapped from the cube while the hand is far out; the wand rolls slowly about its axis.
    The body origin is sensor 0 and body x runs from the tip to the hand (``ivc.sim.rig`` frames).
    """
    volume, spec = scene.volume, scene.extension
    if volume is None:
        raise ValueError("extension sweeps need the scene's working volume")
    times = np.arange(frames) / scene.sweep_rate_hz
    amplitude = np.maximum(volume.size / 2 - HAND_MARGIN, 0.01)
    ratios = np.array([1.0, 0.79, 0.61]) * rng.uniform(0.9, 1.1, 3)
    frequency = spec.speed / (2 * np.pi * amplitude) * ratios / np.sqrt(np.sum(ratios**2) / 2)
    phase = rng.uniform(0, 2 * np.pi, 3)
    hand = volume.center + amplitude * np.sin(2 * np.pi * frequency * times[:, None] + phase)
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
