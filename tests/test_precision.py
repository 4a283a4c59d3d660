"""Predicted precision of corrected poses: the signal noise measured from static steps, the bound
against Monte Carlo corrections, the LOW_PRECISION flag, and the CLI's columns."""

import numpy as np
import pytest
from click.testing import CliRunner

from ivc import dipole, rotations
from ivc.cli import cli
from ivc.collect.replay import read_csv_columns, write_csv
from ivc.correct import LOW_PRECISION, Corrector
from ivc.errors import InputError
from ivc.lut import LookupTable
from ivc.lut.signal_noise import measure_signal_noise
from ivc.pose.precision import pose_covariance, pose_precision
from ivc.pose.tracker_solver import distortion
from ivc.session import Session, Step
from ivc.sim.noise_floor import finite_difference_jacobian
from tests.helpers import CENTRE, quadratic_field


def _static_step(rng, frames, sensors, sigma, drift=0.0, dropouts=0.0, relative=False):
    """Static sensors 0.3-0.8 m from the source, white noise ``sigma`` per entry (``relative``: ``sigma`` times
    each sensor's rms entry), a slow random-walk gain drift of each source coil, and random dropouts."""
    r = rng.uniform(0.3, 0.8, (sensors, 1)) * rotations.to_matrix(rotations.random(sensors, rng))[:, 0]
    S = np.broadcast_to(dipole.signal(r, rotations.to_matrix(rotations.random(sensors, rng))),
                        (frames, sensors, 3, 3)).copy()
    S *= 1 + np.cumsum(drift * rng.standard_normal((frames, 1, 1, 3)), axis=0)
    level = np.sqrt(np.mean(S[0] ** 2, axis=(1, 2)))[None, :, None, None] if relative else 1.0
    S += sigma * level * rng.standard_normal(S.shape)
    valid = rng.random((frames, sensors)) >= dropouts
    S[~valid] = np.nan
    return Step(np.arange(frames) / 240.0, S, valid=valid)


def test_signal_noise_of_static_steps_is_the_white_noise_despite_drift_and_dropouts(rng):
    sigma = 3e-4
    session = Session("+x", {"cube_calibration": _static_step(rng, 1500, 8, sigma, drift=2e-5, dropouts=0.01),
                             "cube_survey": _static_step(rng, 300, 8, sigma),
                             "wand_calibration": _static_step(rng, 300, 4, sigma),
                             "wand_sweep": _static_step(rng, 300, 4, 100 * sigma)})  # not static: not used
    noise = measure_signal_noise(session)
    assert noise.sigma == pytest.approx(sigma, rel=0.03)
    assert noise.steps == ("cube_calibration", "cube_survey", "wand_calibration")
    assert noise.spread < 1.3
    assert noise.pairs > 0.95 * (1499 + 299) * 8 + 0.95 * 299 * 4
    relative = measure_signal_noise(Session("+x", {"cube_calibration": _static_step(rng, 500, 8, 1e-3,
                                                                                    relative=True)}))
    assert relative.spread > 3  # the nearest sensors are noisiest: the absolute-noise assumption is visibly off


def test_no_signal_noise_without_static_signals(rng):
    poses_only = Step(np.arange(50) / 240.0, None, np.full((50, 2, 3), 0.5), np.tile([1.0, 0, 0, 0], (50, 2, 1)))
    assert measure_signal_noise(Session("+x", {"cube_calibration": poses_only})) is None
    frozen = _static_step(rng, 100, 2, 0.0)
    assert measure_signal_noise(Session("+x", {"cube_calibration": frozen})) is None


def test_predicted_precision_is_the_spread_of_noisy_corrections_and_the_bound_at_the_true_pose(exact_table, rng):
    sigma = 2e-4
    r = CENTRE + np.array([0.1, -0.05, 0.08])
    q = rotations.random(1, rng)
    T = rotations.to_matrix(q)[0]
    trials = 2000
    S = T.T @ (dipole.field(r) + quadratic_field(r[None])[0]) + sigma * rng.standard_normal((trials, 3, 3))
    out = Corrector(exact_table, precision=True, signal_noise=sigma).batch(S)
    assert np.all(out.flags == 0)
    rms = np.sqrt(np.mean(np.sum((out.position - r) ** 2, axis=1)))
    angle = rotations.angle_between(out.quaternion, np.broadcast_to(q, out.quaternion.shape))
    assert rms == pytest.approx(np.median(out.precision), rel=0.08)
    assert np.sqrt(np.mean(angle**2)) == pytest.approx(np.median(out.orientation_precision), rel=0.08)
    # at the true pose, from the true field (finite differences), the bound is the same to the table's accuracy
    true_r, true_a = pose_precision(r[None], q, sigma, finite_difference_jacobian(quadratic_field))
    assert np.median(out.precision) == pytest.approx(true_r[0], rel=0.02)
    assert np.median(out.orientation_precision) == pytest.approx(true_a[0], rel=0.02)


def test_a_pose_whose_residual_exceeds_the_noise_gets_a_wider_precision(exact_table, rng):
    """Where the room's field differs from the table's (a field error the table does not hold, about 40 times the
    noise, in a direction of its own at every pose), the noise alone predicts the poses' error ten times too small,
    and each pose's residual says so: its precision is widened by the residual's excess over the noise (never
    narrowed), and actual / predicted comes back near 1 (the part of the error a pose change can mimic stays
    unseen: a few poses remain beyond 5x). Where only the noise is, the prediction is the noise's (a residual
    over twice the noise's variance is rare)."""
    from ivc.correct.precision import RESIDUAL_EXCESS, residual_widening

    sigma = 1e-4
    n = 400
    r = CENTRE + 0.12 * rng.uniform(-1, 1, (n, 3))
    T = rotations.to_matrix(rotations.random(n, rng))
    error = 40 * sigma * rng.standard_normal((n, 3, 3)) / 3  # |error|_F about 40 sigma
    corrector = Corrector(exact_table, signal_noise=sigma, max_precision=None)
    for off, field in ((True, quadratic_field(r) + error), (False, quadratic_field(r))):
        S = dipole.signal(r, T, field) + sigma * rng.standard_normal((n, 3, 3))
        out = corrector.batch(S)
        assert np.all(out.flags == 0)
        noise_only = corrector.predict_precision(out.position, out.quaternion)[0]
        widening = out.precision / noise_only
        assert np.all(widening >= 1 - 1e-9)
        np.testing.assert_allclose(widening, residual_widening(out.residual, S, sigma), rtol=1e-9)
        ratio, noise_ratio = (np.linalg.norm(out.position - r, axis=1) / p for p in (out.precision, noise_only))
        if off:
            assert np.mean(noise_ratio > 5) > 0.5  # the noise alone: far too optimistic
            assert np.mean(ratio > 5) < 0.1 and 0.5 < np.median(ratio) < 2.0
        else:
            assert np.mean(widening > 1 + 1e-9) < 0.2 and np.median(widening) == pytest.approx(1.0, abs=1e-9)
            assert np.mean(ratio > 5) == 0
    # the factor itself: sqrt of the residual's variance over RESIDUAL_EXCESS times the noise's share (3 sigma^2)
    S = np.eye(3)[None].repeat(3, 0)
    rho = np.sqrt(3 * sigma**2 * RESIDUAL_EXCESS * np.array([0.5, 1.0, 4.0])) / np.sqrt(3)
    np.testing.assert_allclose(residual_widening(rho, S, sigma), [1.0, 1.0, 2.0])
    assert residual_widening(np.array([np.nan]), S[:1], sigma)[0] == 1.0


def test_covariance_is_symmetric_positive_and_scales_with_the_noise_squared(rng):
    r = CENTRE + 0.1 * rng.standard_normal((5, 3))
    q = rotations.random(5, rng)
    C1, C2 = pose_covariance(r, q, 1e-4), pose_covariance(r, q, 3e-4)
    np.testing.assert_allclose(C1, np.swapaxes(C1, 1, 2), rtol=1e-9, atol=1e-30)
    assert np.all(np.linalg.eigvalsh(C1) > 0)
    np.testing.assert_allclose(C2, 9 * C1, rtol=1e-12)
    with pytest.raises(InputError):
        pose_covariance(r, q[:2], 1e-4)


def test_low_precision_flag_follows_the_limit_and_needs_a_noise(exact_table, rng):
    r = CENTRE + 0.15 * rng.uniform(-1, 1, (400, 3))
    T = rotations.to_matrix(rotations.random(400, rng))
    S = dipole.signal(r, T, quadratic_field(r))
    predicted = Corrector(exact_table, precision=True, signal_noise=1e-4).batch(S).precision
    limit = float(np.median(predicted))
    out = Corrector(exact_table, max_precision=limit, signal_noise=1e-4).batch(S)
    np.testing.assert_array_equal((out.flags & LOW_PRECISION) != 0, predicted > limit)
    unknown = Corrector(exact_table)  # this table was not fitted from a session: no noise recorded
    assert unknown.batch(S).precision is None and "no signal noise" in unknown.gate.describe()
    assert Corrector(exact_table, precision=False).gate.note == "precision not predicted (precision=False)"
    with pytest.raises(InputError, match="signal noise"):
        Corrector(exact_table, max_precision=1e-3)  # a limit the corrector cannot apply is refused, not ignored
    default = Corrector(exact_table, signal_noise=1e-4)  # the default gate: 1 mm wherever the noise is known
    np.testing.assert_array_equal((default.batch(S).flags & LOW_PRECISION) != 0, predicted > 1e-3)
    with pytest.raises(InputError):
        Corrector(exact_table, max_precision=-1.0, signal_noise=1e-4)
    live = Corrector(exact_table, max_precision=limit, signal_noise=1e-4)
    streamed = np.concatenate([live.update(frame).flags for frame in S.reshape(100, 4, 3, 3)])
    np.testing.assert_array_equal(streamed, out.flags)  # the live path (a few sensors, NumPy forms) agrees
    nan = S.copy()
    nan[0] = np.nan
    out = Corrector(exact_table, precision=True, signal_noise=1e-4).batch(nan)
    assert np.isnan(out.precision[0]) and np.isfinite(out.precision[1:]).all()


def test_cli_writes_precision_columns_and_flags(exact_table, tmp_path, rng):
    table = LookupTable(exact_table.grid, exact_table.values, exact_table.valid, exact_table.support,
                        fit={"signal_noise": {"sigma": 1e-4}})
    from ivc.lut import write

    write(table, tmp_path / "t.h5")
    r = CENTRE + 0.1 * rng.uniform(-1, 1, (30, 1, 3))
    q = rotations.random((30, 1), rng)
    S = dipole.signal(r, rotations.to_matrix(q), quadratic_field(r.reshape(-1, 3)).reshape(30, 1, 3, 3))
    write_csv(Step(np.arange(30) / 240.0, S, r, q), tmp_path / "in.csv")
    result = CliRunner().invoke(cli, ["correct", str(tmp_path / "t.h5"), str(tmp_path / "in.csv"), "-o",
                                      str(tmp_path / "out.csv"), "--max-precision", "0.05"])
    assert result.exit_code == 0, result.output
    assert "predicted precision" in result.output
    _, columns = read_csv_columns(tmp_path / "out.csv")
    expected = 1000 * Corrector(table, precision=True).batch(S).precision
    written = np.array(columns.extra["precision_mm"], float).reshape(expected.shape)
    np.testing.assert_allclose(written, expected, rtol=1e-6)
    flags = np.array(columns.extra["flags"], float).astype(int).reshape(expected.shape)
    np.testing.assert_array_equal((flags & LOW_PRECISION) != 0, expected > 0.05)
    # reported poses get a prediction too: the tracker's noise carried through the inverse map, close to the
    # signal path's (the same noise and field; the reported pose's scatter is taken as a free-space solve's)
    v, C = distortion(r.reshape(-1, 3), quadratic_field(r.reshape(-1, 3)))
    poses = Step(np.arange(30) / 240.0, None, v.reshape(30, 1, 3),
                 rotations.from_matrix(C @ rotations.to_matrix(q.reshape(-1, 4))).reshape(30, 1, 4))
    write_csv(poses, tmp_path / "poses.csv")
    result = CliRunner().invoke(cli, ["correct", str(tmp_path / "t.h5"), str(tmp_path / "poses.csv"), "-o",
                                      str(tmp_path / "out2.csv"), "--max-precision", "none"])
    assert result.exit_code == 0, result.output
    assert "no precision gate" in result.output
    _, columns = read_csv_columns(tmp_path / "out2.csv")
    from_poses = np.array(columns.extra["precision_mm"], float).reshape(expected.shape)
    np.testing.assert_allclose(from_poses, expected, rtol=0.1)
