"""Adelstein, Jung & Ellis 2001: the 10-state quaternion EKF and the predictive-compensator optimisation."""

import numpy as np
import pytest
from scipy import signal
from scipy.linalg import expm

from ivc import rotations
from ivc.predict import make
from ivc.predict.nasa import DEFAULT_W, N, NasaEKF, expm_taylor, jacobian, omega_matrix, q_matrix
from ivc.predict.studies import compensator


def _kinematics(x):
    """ẋ = [½ q ⊗ (0, ω), α, 0]."""
    q, w, a = x[:4], x[4:7], x[7:]
    return np.concatenate([0.5 * rotations.multiply(q, np.r_[0.0, w]), a, np.zeros(3)])


def test_q_and_omega_matrices_give_the_quaternion_product(rng):
    """Eq. 18 (corrected) and eq. 19: q ⊗ (0, ω) = Q_r(q) ω = Ω_r(ω) q."""
    for _ in range(5):
        q, w = rotations.random(1, rng)[0], rng.normal(0, 2, 3)
        Q, Om = np.empty((4, 3)), np.empty((4, 4))
        q_matrix(q, Q)
        omega_matrix(w, Om)
        product = rotations.multiply(q, np.r_[0.0, w])
        assert np.allclose(Q @ w, product, atol=1e-15) and np.allclose(Om @ q, product, atol=1e-15)


def test_jacobian_against_finite_differences_and_the_doubled_rate(rng):
    x = np.r_[rotations.random(1, rng)[0], rng.normal(0, 2, 3), rng.normal(0, 10, 3)]
    F = np.empty((N, N))
    jacobian(x, F)
    eps = 1e-6
    numeric = np.stack([(_kinematics(x + eps * e) - _kinematics(x - eps * e)) / (2 * eps) for e in np.eye(N)], 1)
    assert np.allclose(F, numeric, atol=1e-8)
    # docs/math.md §17.1: F x is twice the quaternion rate (why eq. 20 must not propagate the state)
    assert np.allclose((F @ x)[:4], 2 * _kinematics(x)[:4])


def test_structured_taylor_expm_matches_scipy(rng):
    for scale in (1.0, 5.0):
        x = np.r_[rotations.random(1, rng)[0], rng.normal(0, 3 * scale, 3), rng.normal(0, 30, 3)]
        F = np.empty((N, N))
        jacobian(x, F)
        out = np.empty((N, N))
        expm_taylor(F / 120.0, out, np.empty((N, N)), np.empty((N, N)))
        assert np.abs(out - expm(F / 120.0)).max() < 1e-12  # as EXPM_TERMS promises, up to 15 rad/s


def test_constant_rate_and_acceleration_are_predicted_exactly(rng):
    """Noise-free rotation with constant body rates (ω, then ω + αt about a fixed axis): exact at 50 ms."""
    rate, t = 120.0, np.arange(1500) / 120.0
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    q0 = rotations.random(1, rng)[0]
    for angle in (1.7 * t, 1.2 * t + 0.5 * 0.8 * t**2):  # constant ω; constant α (same axis: exact kinematics)
        q = rotations.multiply(q0, rotations.from_rotvec(angle[:, None] * axis))
        predicted = NasaEKF(rate).predict(q, 0.05)[0]
        k = np.arange(900, len(t) - 6)
        assert rotations.angle_between(predicted[k], q[k + 6]).max() < 1e-6


def test_sign_flips_and_streaming_change_nothing(rng):
    rate = 120.0
    q = rotations.multiply(rotations.random(1, rng)[0], rotations.from_rotvec(np.outer(np.arange(300) / rate,
                                                                                       [0.4, 1.1, -0.7])))
    q = rotations.multiply(q, rotations.from_rotvec(rng.normal(0, 1e-3, (300, 3))))
    flipped = q * np.where(rng.random(300) < 0.5, -1.0, 1.0)[:, None]
    predictor = make("nasa-ekf", rate)
    batch = predictor.predict(q, 0.05)[0]
    assert np.allclose(rotations.angle_between(predictor.predict(flipped, 0.05)[0, 1:], batch[1:]), 0.0, atol=1e-9)
    stream = predictor.stream(1)
    live = []
    for frame in flipped:
        stream.update(frame[None])
        live.append(stream.predict(0.05)[0])
    assert np.allclose(rotations.angle_between(np.array(live)[1:], batch[1:]), 0.0, atol=1e-9)


def test_high_pass_filter_matches_the_notes_magnitudes():
    """H(s) = s²/((s + 2π·0.5)(s + 2π·5)): |H| = 0.0704, 0.3603, 0.7036 at 0.5, 2, 5 Hz (bilinear, 120 Hz)."""
    p1, p2 = 2 * np.pi * 0.5, 2 * np.pi * 5.0
    b, a = signal.bilinear([1.0, 0.0, 0.0], [1.0, p1 + p2, p1 * p2], fs=120.0)
    _, response = signal.freqz(b, a, worN=[0.5, 2.0, 5.0], fs=120.0)
    assert np.abs(response) == pytest.approx([0.0704, 0.3603, 0.7036], rel=0.01)
    t = np.arange(2400) / 120.0
    q = rotations.from_rotvec(np.outer(0.01 * np.sin(2 * np.pi * 5.0 * t), [0, 1, 0]) + [0, 0, 0.3])
    filtered = rotations.to_rotvec(compensator.high_pass(q, 120.0))[1200:, 1]
    assert np.sqrt(2) * filtered.std() == pytest.approx(0.01 * 0.7036, rel=0.03)  # the offset is gone, 5 Hz kept


def test_displacement_and_twist_of_a_two_degree_yaw():
    """docs/math.md §17.3: a 2° yaw error moves the target 0.8 m ahead by Δy = 27.92 mm, Δx = −0.49 mm."""
    error = rotations.from_rotvec([0.0, 0.0, np.radians(2.0)])
    d = compensator.displacement(error, rotations.IDENTITY)
    assert d == pytest.approx([-0.000487, 0.027919, 0.0], abs=2e-6)
    assert compensator.twist(error, -rotations.IDENTITY) == pytest.approx(np.radians(2.0))


@pytest.mark.slow
def test_optimised_designs_reproduce_the_papers_orderings():
    """Table 1's reading: the twist design is best on twist; the hybrid suppresses vertical noise (to about no
    prediction) where default and twist amplify it, and gives up twist accuracy to do so."""
    records = compensator.yaw_records(seconds=10.0, seed=3)
    default = compensator.score(np.array(DEFAULT_W), records).ratios
    twist = compensator.score(compensator.optimise("twist", records, max_evaluations=300)[0], records).ratios
    hybrid = compensator.score(compensator.optimise("hybrid", records, max_evaluations=300)[0], records).ratios
    assert twist[0] < default[0] and twist[0] < hybrid[0]
    assert hybrid[4] < 0.75 * default[4] and hybrid[4] < 0.75 * twist[4]
    assert default[4] > 1.5 and twist[4] > 1.0  # prediction amplifies tremor
    assert default[0] < 1.0 and twist[0] < 1.0  # and beats no prediction on twist; the hybrid's costs are blind
    # to roll about the line of sight (the target does not move), so its twist may be anything
