"""Builders shared by the test modules (no test module imports another)."""

import numpy as np

from ivc import dipole, rotations
from ivc import rotations as R
from ivc.dipole.tracker import Tracker
from ivc.lut import harmonics
from ivc.lut.samples import FieldSamples
from ivc.pose.calibrate import Fixtures, rigid_transform
from ivc.predict.delta import delta_q
from ivc.session import Session, Step, Truth
from ivc.sim.scene import NoiseSpec
from ivc.sim.tracker import measure


def random_positions(rng, n, low=0.05, high=2.0, hemisphere=None):
    """Random positions with range uniform in [low, high] metres, directions uniform."""
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if hemisphere is not None:
        d *= np.where(d @ hemisphere < 0, -1.0, 1.0)[:, None]
    return d * rng.uniform(low, high, (n, 1))


def make_step(rng, frames=20, sensors=8, with_signal=True, with_pose=True):
    position = np.array([0.5, 0.0, 0.0]) + 0.05 * rng.standard_normal((frames, sensors, 3))
    quaternion = R.random((frames, sensors), rng)
    return Step(
        time=np.arange(frames) / 240.0,
        signal=dipole.signal_from_pose(position, quaternion) if with_signal else None,
        position=position if with_pose else None,
        quaternion=quaternion if with_pose else None,
        valid=rng.random((frames, sensors)) > 0.1,
        sample_rate_hz=240.0,
        sensor_ids=[f"s{i}" for i in range(sensors)],
        description="test data",
    )


def survey_attrs():
    return {"declared_position": np.array([0.5, 0.01, -0.02]), "declared_quaternion": np.array([1.0, 0, 0, 0])}


def full_session(rng):
    survey = make_step(rng)
    survey.attrs = survey_attrs()
    steps = {
        "cube_calibration": make_step(rng),
        "cube_survey": survey,
        "wand_calibration": make_step(rng, sensors=5),
        "wand_sweep": make_step(rng, frames=50, sensors=5, with_pose=False),
        "check": make_step(rng, frames=7, sensors=3, with_signal=False),
    }
    truth = {"check": Truth(steps["check"].position.copy(), steps["check"].quaternion.copy())}
    return Session(hemisphere="+x", steps=steps, truth=truth)


CENTRE = np.array([0.5, 0.0, 0.0])


def external_dipole_field(r):
    """A smooth harmonic 3x3 field, about 10 % of the primary: columns are fields of three dipoles 0.6 m
    from the centre (outside the mapped ball)."""
    sources = CENTRE + np.array([[0.6, 0, 0], [0, 0.6, 0], [0, 0, -0.6]])
    moments = np.array([[0.06, 0.03, 0.0], [0.0, -0.05, 0.03], [0.03, 0.0, 0.06]])
    G = np.zeros(np.shape(r)[:-1] + (3, 3))
    for p, m in zip(sources, moments, strict=True):
        G += dipole.field(r - p) @ np.diag(m) @ np.ones((3, 3)) / 3  # each source feeds every column
    return G


def quadratic_field(r):
    """Columns = gradients of degree-3 harmonic potentials: a field exactly quadratic in r."""
    x = r - CENTRE
    basis = harmonics.gradients(x / 0.2, 3)  # (N, 15, 3)
    coefficients = np.linspace(-1, 1, 45).reshape(15, 3) * 0.5  # about 10 % of the primary field
    return np.einsum("nki,kj->nij", basis, coefficients)


def ball(rng, n, radius, centre=CENTRE):
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return centre + d * radius * rng.random((n, 1)) ** (1 / 3)


def samples_of(field, positions):
    n = len(positions)
    return FieldSamples(positions, field(positions), np.zeros(n), np.arange(n) // 8, np.arange(n) % 8)


def static_capture(fixture, position, quaternion, frames=50, noise=None, rng=0):
    positions, quaternions = fixture.sensor_poses(np.asarray(position)[None], np.asarray(quaternion)[None])
    positions, quaternions = np.repeat(positions, frames, 0), np.repeat(quaternions, frames, 0)
    return measure(positions, quaternions, secondary=None, noise=noise or NoiseSpec.none(), rate_hz=240,
                   hemisphere="+x", rng=np.random.default_rng(rng))


def distorted(rng, n, radius=0.18):
    r = ball(rng, n, radius)
    T = rotations.to_matrix(rotations.random(n, rng))
    return r, T, dipole.signal(r, T, quadratic_field(r))


def imperfect_tracker(rng, offsets=True, scale=0.05):
    """A miscalibrated device: percent gains, cross-talk, millimetre coil offsets."""
    return Tracker(np.eye(3) + scale * rng.standard_normal((3, 3)), np.eye(3) + scale * rng.standard_normal((3, 3)),
                   2e-3 * rng.standard_normal((3, 3)) if offsets else np.zeros((3, 3)),
                   1e-3 * rng.standard_normal((3, 3)) if offsets else np.zeros((3, 3)))


def rig_fixtures(rng):
    """A stage rig's fixtures: the stage 0.25 m out along +y, small tilts and offsets."""

    def small(t):
        return rigid_transform(rotations.to_matrix(rotations.from_rotvec(0.03 * rng.standard_normal(3))), t)

    return Fixtures(np.eye(4), small(np.array([0.01, 0.25, -0.01])), small(0.005 * rng.standard_normal(3)))


def reported_matrices(S):
    """What a tracker reports for signals S (..., 3, 3): the dipole solution as 4x4 matrices with translations
    in mm, in float32 as OpenIGTLink carries them."""
    position, rotation = dipole.closed_form_pose(S)
    m = np.zeros((*S.shape[:-2], 4, 4))
    m[..., :3, :3], m[..., :3, 3], m[..., 3, 3] = rotation, position * 1000.0, 1.0
    return m.astype(np.float32)


def wandering_head(rng, n=900):
    """A smooth random head motion (t (n,) s at jittered 12-22 ms steps, q (n, 4)) with a stale frame every 23
    from frame 200 (the sample repeated)."""
    t = np.cumsum(rng.uniform(0.012, 0.022, n))
    w = np.stack([np.convolve(rng.normal(0, 3.0, n + 40), np.ones(40) / 40, "valid")[:n] for _ in range(3)], 1)
    q = np.empty((n, 4))
    q[0] = rotations.random(1, rng)[0]
    for k in range(1, n):
        q[k] = rotations.multiply(delta_q(w[k] * (t[k] - t[k - 1]), 1.0), q[k - 1])
    q[200::23] = q[199::23][: len(q[200::23])]  # stale frames
    return t, q
