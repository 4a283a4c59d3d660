"""Orientation predictors: Δq and its Jacobian, exactness on constant rates, streaming = batch, bad input."""

import numpy as np
import pytest
from scipy.linalg import expm

from ivc import rotations
from ivc.predict import FILTERS, PredictorError, make
from ivc.predict import quat as Q
from ivc.predict.delta import delta_q, delta_q_jacobian, deltas, extrapolate, rate_from_delta
from ivc.predict.dq import PI_MMDQ3, SIGMA_CA, SIGMA_CV1, SIGMA_DQ, DQPredictor, Model, dqekf_cv, mmdq2, mmdq3
from ivc.predict.motion import head_motion

TAU = 1.0 / 120.0


def psi(w):
    """Eq. 12: ½ L([0, ω]) (the thesis's Ψ)."""
    a, b, c = w
    return 0.5 * np.array([[0, -a, -b, -c], [a, 0, -c, b], [b, c, 0, -a], [c, -b, a, 0]])


def test_delta_q_is_the_matrix_exponential_of_psi_and_inverts(rng):
    for w in rng.normal(0, 3, (20, 3)):
        t = rng.uniform(0.001, 0.2)
        dq = delta_q(w, t)
        assert np.isclose(np.linalg.norm(dq), 1.0)
        q = rotations.random(1, rng)[0]
        assert np.allclose(expm(psi(w) * t) @ q, rotations.multiply(dq, q), atol=1e-13)
        assert np.allclose(dq, rotations.from_rotvec(w * t), atol=1e-14)
        assert np.allclose(rate_from_delta(dq, t), w, atol=1e-10)
    assert np.allclose(delta_q(np.zeros(3), 0.1), [1, 0, 0, 0])


@pytest.mark.parametrize("scale", [0.0, 1e-9, 1e-5, 0.3, 4.0])
def test_delta_q_jacobian_matches_finite_differences(rng, scale):
    """Including ω = 0, where the printed eq. 22 divides by zero."""
    for _ in range(5):
        w = rng.normal(0, 1, 3) * scale
        J = delta_q_jacobian(w, TAU)
        Jk = np.empty((4, 3))
        value = np.empty(4)
        Q.delta_q_jacobian(w[0], w[1], w[2], TAU, Jk, value)
        assert np.allclose(value, delta_q(w, TAU), atol=1e-16)
        h = 1e-6
        fd = np.stack([(delta_q(w + h * e, TAU) - delta_q(w - h * e, TAU)) / (2 * h) for e in np.eye(3)], axis=1)
        assert np.allclose(J, fd, atol=1e-10, rtol=1e-7)
        assert np.allclose(Jk, J, atol=1e-15)
        out = np.empty(4)
        Q.delta_q(w[0], w[1], w[2], TAU, out)
        assert np.allclose(out, delta_q(w, TAU), atol=1e-16)
    # the literal eq. 22 has τ/4 and τ where τ/2 is right: its small-rate diagonal would be τ, not τ/2
    assert np.allclose(delta_q_jacobian(np.zeros(3), TAU)[1:], 0.5 * TAU * np.eye(3))



@pytest.mark.parametrize("name", ["dqekf-cv", "dqekf-ca", "mmdq2", "mmdq3", "q-ekf"])
def test_constant_angular_velocity_is_predicted_exactly_at_any_horizon(rng, name):
    n = 400
    w = rng.normal(0, 1.0, 3)
    q0 = rotations.random(1, rng)[0]
    t = np.arange(n) * TAU
    q = rotations.multiply(delta_q(w * t[:, None], 1.0), q0)
    horizons = np.array([0.0, 0.0041, 0.05, 0.0789, 0.1167, 0.3])
    pred = make(name).predict(q, horizons)
    truth = rotations.multiply(delta_q(w * (t[None, :, None] + horizons[:, None, None]), 1.0), q0)
    err = rotations.angle_between(pred[:, 2:], truth[:, 2:])
    assert np.all(np.isfinite(err))
    assert err.max() < 1e-11


def test_extrapolate_fractional_frames_and_zero_acceleration():
    q = rotations.random(3, 0)
    w = np.array([[0.3, -1, 2]] * 3)
    assert np.allclose(extrapolate(q, w, np.zeros((3, 3)), 0.0123, TAU), rotations.multiply(delta_q(w, 0.0123), q))
    # with α, whole frames use ω + nτα and the rest of a frame the next rate (docs/math.md §11.4, corrected)
    a = np.array([[0.0, 0, 30]] * 3)
    got = extrapolate(q, w, a, 2.5 * TAU, TAU)
    ref = q
    for n, span in ((1, TAU), (2, TAU), (3, 0.5 * TAU)):
        ref = rotations.multiply(delta_q(w + n * TAU * a, span), ref)
    assert np.allclose(got, ref, atol=1e-14)
    with pytest.raises(ValueError):
        extrapolate(q, w, None, -0.01, TAU)


def test_deltas_force_a_non_negative_scalar_part(rng):
    q = rotations.random(50, rng)
    q[1::2] *= -1
    d = deltas(q)
    assert np.all(d[:, 0] >= 0)


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_streaming_equals_batch_with_gaps(name):
    """Two sensors, a NaN sample and an invalid frame: the live form reproduces the batch one."""
    a = head_motion("moderate", 600, seed=3).measured
    b = head_motion("aggressive", 600, seed=4).measured
    q = np.stack([a, b], axis=1)
    q[100, 0] = np.nan
    valid = np.ones((600, 2), bool)
    valid[200:203, 1] = False
    predictor = make(name)
    batch = predictor.predict(q, [0.05], valid)[0]
    stream = predictor.stream(2)
    live = np.empty_like(batch)
    for k in range(600):
        stream.update(q[k], valid[k])
        live[k] = stream.predict(0.05)
    assert np.array_equal(np.isnan(batch), np.isnan(live))
    assert np.nanmax(np.abs(batch - live)) < 1e-9
    assert np.all(np.isnan(batch[100, 0])) and np.all(np.isnan(batch[201, 1]))
    assert np.isfinite(batch[300:]).all()


def _dense_dq_ekf(z, qv, ca, h_jacobian):
    """Textbook EKF on the Δq stream, NumPy matrices: the reference for the compiled kernel's shortcuts."""
    n = 6 if ca else 3
    R = np.diag(np.square(SIGMA_DQ))
    x = np.zeros(n)
    x[:3] = rate_from_delta(z[0], TAU)
    P = np.diag([1.0] * 3 + [100.0] * (n - 3))
    I3 = np.eye(3)
    if ca:
        A = np.block([[I3, TAU * I3], [np.zeros((3, 3)), I3]])
        W = np.vstack([TAU**2 / 2 * I3, TAU * I3])
    else:
        A, W = I3, TAU * I3
    shift = -0.5 * TAU if ca and h_jacobian == "midpoint" else 0.0
    c = {"standard": 0.0, "thesis": TAU, "midpoint": shift}[h_jacobian]
    out = [x.copy()]
    for zk in z[1:]:
        xp, Pp = A @ x, A @ P @ A.T + W @ np.diag(qv) @ W.T
        w = xp[:3] + (shift * xp[3:] if ca else 0.0)
        J = delta_q_jacobian(w, TAU)
        H = np.hstack([J, c * J]) if ca else J
        S = H @ Pp @ H.T + R
        K = Pp @ H.T @ np.linalg.inv(S)
        x = xp + K @ (zk - delta_q(w, TAU))
        IKH = np.eye(n) - K @ H
        P = IKH @ Pp @ IKH.T + K @ R @ K.T
        out.append(x.copy())
    return np.array(out)


@pytest.mark.parametrize("model, h_jacobian", [("cv", "standard"), ("ca", "standard"), ("ca", "thesis"),
                                               ("ca", "midpoint")])
def test_dq_ekf_equals_a_dense_textbook_ekf(model, h_jacobian):
    """The kernel skips H's zero columns, the identity block of I − KH and half of S: same filter, every variant."""
    q = head_motion("aggressive", 400, seed=3).measured
    sigma = SIGMA_CA if model == "ca" else SIGMA_CV1
    predictor = DQPredictor([Model(model, sigma)], 120.0, h_jacobian=h_jacobian)
    _, est, usable, _ = predictor.filter(q)
    assert usable[1:].all() and not usable[0]
    reference = _dense_dq_ekf(deltas(q), np.square(sigma), model == "ca", h_jacobian)
    n = reference.shape[1]
    scale = np.abs(reference).max(axis=0)  # ω in rad/s, α in rad/s²: each relative to its own size
    np.testing.assert_allclose((est[1:, 0, :n] - reference) / scale, 0.0, atol=1e-9)
    assert not np.any(est[:, 0, n:])


@pytest.mark.parametrize("name", ["dqekf-cv", "mmdq2"])
def test_a_diverged_filter_restarts_and_recovers(name):
    """Every model's covariance NaN (a diverged filter): the filter restarts from the next Δq with a fresh P.

    A single DQ-EKF then equals a fresh filter; the IMM keeps its mode probabilities and TPM, so it is close to one.
    """
    q = head_motion("moderate", 60, seed=2).measured
    stream = make(name).stream(1)
    for k in range(30):
        stream.update(q[k:k + 1])
    stream.state[1][:] = np.nan  # P of every model
    for k in range(30, 34):
        stream.update(q[k:k + 1])
    assert stream.ready[0] and np.all(np.isfinite(stream.state[1]))
    reference = make(name).rates(q[30:34])[-1]  # a fresh filter started from the same Δq
    np.testing.assert_allclose(stream.omega[0], reference, rtol=1e-12 if name == "dqekf-cv" else 0.1)


def test_imm_probabilities_and_adaptive_tpm_stay_stochastic():
    motion = head_motion("full", 3000, seed=5)
    q = motion.measured
    predictor = mmdq3()
    _, est, usable, mu = predictor.filter(q)
    m = mu[usable[:, 0], 0]
    assert np.allclose(m.sum(axis=1), 1.0)
    assert m.min() >= 1e-4 / (1 + 3e-4)  # floor, renormalised
    # the CA models win during the fast bursts, the CV model when still
    accel = np.r_[0.0, np.linalg.norm(np.diff(motion.omega, axis=0), axis=1) * 120.0]
    ca = mu[:, 0, 1:].sum(axis=1)
    assert ca[usable[:, 0] & (accel > 5)].mean() > 2 * ca[usable[:, 0] & (accel < 0.5)].mean()
    stream = predictor.stream(1)
    for k in range(500):
        stream.update(q[k:k + 1])
    Pi = stream.state[3][0, 0]
    assert np.allclose(Pi.sum(axis=1), 1.0) and Pi.min() >= 1e-50
    assert not np.allclose(Pi, np.array(PI_MMDQ3))  # it adapted


def test_variant_switches_change_the_ca_filter():
    q = head_motion("aggressive", 2000, seed=6).measured
    outs = [mmdq2(h_jacobian=h).predict(q, 0.05)[0] for h in ("standard", "thesis", "midpoint")]
    assert not np.allclose(outs[0][10:], outs[1][10:])
    assert not np.allclose(outs[0][10:], outs[2][10:])
    thesis_weights = mmdq2(mode_weights="thesis").predict(q, 0.05)[0]
    assert not np.allclose(outs[0][10:], thesis_weights[10:])
    with pytest.raises(PredictorError):
        mmdq2(h_jacobian="jacobian")
    with pytest.raises(PredictorError):
        mmdq3(mmdq3_models="ca-ca-ca")


def test_bad_input_is_refused_with_a_reason():
    p = dqekf_cv()
    with pytest.raises(PredictorError, match="shape"):
        p.predict(np.zeros((10, 3)), 0.05)
    q = rotations.random(10, 0)
    q[4] *= 1.5
    with pytest.raises(PredictorError, match="frame 4"):
        p.predict(q, 0.05)
    with pytest.raises(PredictorError, match="horizons"):
        p.predict(rotations.random(10, 0), -0.01)
    with pytest.raises(PredictorError, match="unknown filter"):
        make("kalman-magic")
    with pytest.raises(PredictorError, match="shape"):
        p.stream(2).update(rotations.random(3, 0))


def test_synthetic_motion_matches_the_thesis_statistics():
    from ivc.predict.motion import statistics

    s = {m: statistics(head_motion(m, 30_000, seed=1).omega, 120.0) for m in ("benign", "moderate", "aggressive")}
    assert s["benign"]["omega_mean"] < 0.01 and s["benign"]["alpha_max"] < 1.5
    assert 0.25 < s["moderate"]["omega_mean"] < 0.40 and s["moderate"]["omega_max"] < 0.8
    assert 0.8 < s["aggressive"]["omega_mean"] < 1.3 and 10 < s["aggressive"]["alpha_max"] < 25
    # full range (docs/math.md §14.2): α mean 1.0-1.2 rad/s²; its regimes last seconds, so it needs a long record
    full = statistics(head_motion("full", 100_000, seed=1).omega, 120.0)
    assert 1.0 < full["alpha_mean"] < 1.2 and full["alpha_std"] > full["alpha_mean"]
    clean = head_motion("moderate", 500, seed=1, noise_rad=None, dynamic_error=0.0)
    assert np.array_equal(clean.measured, clean.truth)
    # the recorded rate reproduces the orientation: q(k+1) = Δq(ω_k, τ) ⊗ q(k)
    assert np.allclose(rotations.multiply(delta_q(clean.omega[:-1], TAU), clean.truth[:-1]), clean.truth[1:],
                       atol=1e-12)
