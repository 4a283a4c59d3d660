"""Linear predictors (A&B95, NASA) and Kyger's elemental filters (Kyger 1995): closed forms and published values."""

import numpy as np
import pytest
from scipy.integrate import quad

from ivc import rotations
from ivc.predict.base import PredictorError
from ivc.predict.delta import delta_q
from ivc.predict.gains import kinematic_gain
from ivc.predict.linear import alpha_beta, kinematic, polynomial
from ivc.predict.mmae import Elemental, frame_from_axes
from ivc.predict.studies.frequency import (
    AB_CASES,
    AB_PERIOD,
    crossovers,
    polynomial_magnitude,
    polynomial_phase,
    polynomial_response,
    response,
    rms_error,
)


@pytest.mark.parametrize("p, f, magnitude, phase_deg, err", [
    (0.03, 5, 1.0942, 59.468, 0.097032), (0.05, 1, 1.0012, 18.287, 0.003647), (0.05, 5, 1.5881, 98.462, 0.436133),
    (0.05, 10, 5.0351, 141.396, 3.039956), (0.1, 2, 1.2741, 80.494, 0.227045), (0.2, 5, 19.7645, 161.464, 14.647778),
])
def test_polynomial_response_matches_eq_1_and_2_and_the_table(p, f, magnitude, phase_deg, err):
    H = polynomial_response(f, p)
    assert np.isclose(abs(H), polynomial_magnitude(f, p), rtol=1e-12)
    assert np.isclose(np.angle(H), polynomial_phase(f, p), atol=1e-12)
    assert abs(H) == pytest.approx(magnitude, abs=1e-4)
    assert np.degrees(polynomial_phase(f, p)) == pytest.approx(phase_deg, abs=1e-3)
    assert rms_error(H, f, p) == pytest.approx(err, abs=1e-6)


def test_polynomial_phase_is_atan2_and_error_asymptotes():
    for p, f90 in ((0.05, 4.5016), (0.1, 2.2508), (0.2, 1.1254)):
        assert np.degrees(polynomial_phase(f90, p)) == pytest.approx(90.0, abs=0.01)
    phase = polynomial_phase(np.linspace(0.01, 100, 1000), 0.05)
    assert np.all(np.diff(phase) > 0) and phase.max() < np.pi
    # closed-form RMS error equals the period integral of A&B §6.1
    for f, p in ((1.0, 0.05), (7.0, 0.1)):
        H, w = polynomial_response(f, p), 2 * np.pi * f
        P = 1 / f
        def squared_error(t, H=H, w=w, p=p):
            return (abs(H) * np.sin(w * t + np.angle(H) - w * p) - np.sin(w * t)) ** 2

        integral = quad(squared_error, 0, P)[0]
        assert np.sqrt(integral / P) == pytest.approx(rms_error(H, f, p), abs=1e-6)
    u = 0.01
    assert rms_error(polynomial_response(u / (2 * np.pi), 1.0), u / (2 * np.pi), 1.0) == pytest.approx(
        u**3 / (6 * np.sqrt(2)), rel=1e-4)
    assert rms_error(polynomial_response(2.0, 0.05), 2.0, 0.05) == pytest.approx(
        rms_error(polynomial_response(4.0, 0.025), 4.0, 0.025), rel=1e-12)  # depends on ωp only


def test_table_2_sinusoids_gains():
    gains = [abs(polynomial_response(f, 0.03)) for f in (1, 2, 5, 60)]
    assert np.allclose(gains, [1.00016, 1.00252, 1.09419, 63.96285], atol=1e-5)


def test_ab_kalman_cases_published_values_and_crossovers():
    f = np.linspace(0.1, 60, 6000)
    err = {p: {c: rms_error(AB_CASES[c].response(f, p), f, p) for c in (1, 2, 3)} for p in (0.05, 0.2)}
    assert 6.5 < crossovers(f, err[0.05][1], err[0.05][2])[0] < 8.5  # "below ~7 Hz" (Fig. 8)
    assert 15 < crossovers(f, err[0.05][2], err[0.05][3])[0] < 20  # "below ~17 Hz"
    assert 1.8 < crossovers(f, err[0.2][1], err[0.2][2])[0] < 2.4  # "below ~2 Hz" (Fig. 9)
    low = f < 5
    assert np.all(err[0.05][2][low] < err[0.05][1][low])
    assert err[0.05][1][-1] < err[0.05][2][-1]  # Case 1 wins at high frequency
    table = {(0.05, 1.0): (1.0706, 1.0027, 1.0017), (0.1, 2.0): (1.7143, 1.3937, 1.2997),
             (0.2, 5.0): (6.6371, 21.7650, 20.1235)}
    for (p, fi), mags in table.items():
        got = [abs(AB_CASES[c].response([fi], p)[0]) for c in (1, 2, 3)]
        assert np.allclose(got, mags, atol=1e-4)
    poles = np.linalg.eigvals(AB_CASES[1].G(AB_PERIOD))
    assert np.allclose(sorted(poles, key=np.imag), [0.6111 - 0.2420j, 0.6111 + 0.2420j], atol=1e-4)


@pytest.mark.parametrize("case", [1, 2, 3])
def test_ab_low_frequency_invariants(case):
    p, f = 0.1, 1e-4
    O = AB_CASES[case].response([f], p)[0]
    w = 2 * np.pi * f
    assert abs(AB_CASES[case].response([0.0], p)[0] - 1) < 1e-12
    assert ((O - 1) / (1j * w)).real == pytest.approx(p, rel=1e-3)
    second = ((O - 1 - 1j * w * p) / w**2).real
    if case == 1:
        assert abs(second + p * p / 2) > 1e-3  # Case 1 matches e^{jωp} to first order only
    else:
        assert second == pytest.approx(-p * p / 2, rel=1e-2)


@pytest.mark.parametrize("make", [lambda: alpha_beta(200.0), lambda: kinematic(200.0, 1e2, 1e-4),
                                  lambda: polynomial(200.0, 1), lambda: polynomial(200.0, 2)])
def test_time_domain_linear_predictor_equals_its_frequency_response(make):
    """A small yaw sinusoid through the orientation predictor = |O|, ∠O of its (G, K, D) after the transient."""
    predictor = make()
    rate, p, f, amp = 200.0, 0.05, 1.3, 0.02
    t = np.arange(2000) / rate
    angle = amp * np.sin(2 * np.pi * f * t)
    q = delta_q(np.outer(angle, [0.0, 0.0, 1.0]), 1.0)
    pred = predictor.predict(q, p)[0]
    got = 2 * np.arctan2(pred[:, 3], pred[:, 0])
    O = response([f], 1 / rate, predictor.G, predictor.K, predictor.D(p))[0]
    expected = amp * abs(O) * np.sin(2 * np.pi * f * t + np.angle(O))
    assert np.max(np.abs(got[1000:] - expected[1000:])) < 1e-9


@pytest.mark.parametrize("order, window", [(1, 2), (1, 5), (2, 3), (2, 12)])
def test_polynomial_predictor_extrapolates_its_own_order_exactly(order, window):
    """Yaw that is a polynomial of the predictor's order is predicted exactly, fractional horizons too."""
    predictor = polynomial(120.0, order, window)
    t = np.arange(60) / 120.0
    coefficients = [0.1, 0.8, -2.5][:order + 1]
    yaw = np.polynomial.polynomial.polyval(t, coefficients)
    horizon = 0.0437
    pred = predictor.predict(delta_q(np.outer(yaw, [0.0, 0.0, 1.0]), 1.0), horizon)[0]
    got = 2 * np.arctan2(pred[:, 3], pred[:, 0])
    expected = np.polynomial.polynomial.polyval(t + horizon, coefficients)
    assert np.max(np.abs(got[window:] - expected[window:])) < 1e-11


def test_polynomial_window_trades_noise_gain_for_a_longer_fit():
    """The order-1 default is the backward difference; a longer order-2 fit amplifies white noise less."""
    T, p = 1 / 120.0, 0.05
    assert np.allclose(polynomial(120.0, 1).D(p), [1 + p / T, -p / T], atol=1e-12)
    gains = [np.linalg.norm(polynomial(120.0, 2, w).D(p)) for w in (3, 6, 12, 24)]
    assert np.all(np.diff(gains) < 0) and gains[0] > 50 and gains[2] < 4
    assert polynomial(120.0, 2).name == "poly2" and len(polynomial(120.0, 2).K) == 12
    assert len(polynomial(240.0, 2).K) == 24
    with pytest.raises(PredictorError, match="window of at least 3"):
        polynomial(120.0, 2, 2)


def test_kinematic_gain_matches_the_notes_example():
    K = kinematic_gain(1 / 120, 1e-2, 0.01).ravel()
    assert np.allclose(K, [0.0789, 0.389, 0.960], atol=1e-3)
    k = kinematic(120.0, 1e-2, 0.01)
    assert abs(response([0.67], 1 / 120, k.G, k.K, k.D(0.05))[0]) == pytest.approx(1.747, rel=1e-2)


@pytest.mark.parametrize("element, dt, phi, qd", [
    (Elemental("fogma", 5.0, tau=1.0), 0.1, [[1, .1, .00483742], [0, 1, .09516258], [0, 0, .90483742]],
     {(0, 0): 2.36594e-5, (0, 1): 5.85015e-4, (0, 2): 7.54408e-3, (1, 1): 1.54730e-2, (2, 2): 4.53173}),
    (Elemental("fogma", 5.0, tau=10.0), 0.1, [[1, .1, .00498337], [0, 1, .09950166], [0, 0, .99004983]],
     {(0, 0): 2.48616e-6, (1, 2): 2.47515e-2, (2, 2): 0.495033}),
    (Elemental("fogmv", np.sqrt(0.2), tau=0.115), 0.1, [[1, .06679962, 0], [0, .41913374, 0], [0, 0, 1]],
     {(0, 0): 6.34780e-4, (0, 1): 7.76033e-3, (1, 1): 0.164865}),
    (Elemental("phi2", 5.0, tau=5.0), 0.1, [[1, .2, .019736], [0, 1, .196053], [0, 0, .960789]],
     {(0, 0): 4.94484e-6, (2, 2): 0.980264}),
])
def test_gauss_markov_discretisation_matches_the_notes_test_vectors(element, dt, phi, qd):
    """Van Loan Φ and Qd against verified values (docs/math.md §15.2) (the printed q11 of eq. 3.4 is wrong)."""
    Phi, Qd = element.discrete(dt)
    assert np.allclose(Phi[:, :2] if element.kind == "fogmv" else Phi, np.asarray(phi)[:, :2]
                       if element.kind == "fogmv" else phi, atol=1e-6)
    for (i, j), value in qd.items():
        assert Qd[i, j] == pytest.approx(value, rel=1e-4)


def test_steady_state_gain_of_liangs_filter():
    Phi, Qd = Elemental("fogmv", np.sqrt(0.2), tau=0.115).discrete(0.1)
    P = np.diag([1.0, 1.0, 0.0])
    for _ in range(500):
        Pm = Phi @ P @ Phi.T + Qd
        K = Pm[:, 0] / (Pm[0, 0] + 1e-3)
        P = Pm - np.outer(K, Pm[0])
    assert np.allclose(K[:2], [0.71226, 3.81052], atol=1e-4)


def test_frame_from_axes_round_trip(rng):
    q = rotations.random(20, rng)
    T = rotations.to_matrix(q)
    assert np.allclose(rotations.angle_between(frame_from_axes(T[..., 0], T[..., 2] + 0.01 * T[..., 0]), q), 0,
                       atol=1e-7)
