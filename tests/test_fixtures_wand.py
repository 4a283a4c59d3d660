"""Wand calibration, propagation and gating, by rigid-body simulation."""

import numpy as np
import pytest

from ivc import rotations as R
from ivc.fixtures import CubeCalibration
from ivc.fixtures.mapping import FixtureModel, Gates, map_sweep
from ivc.fixtures.wand import WandCalibration
from ivc.session import Session
from ivc.sim import Scene, Simulator
from ivc.sim.scene import NoiseSpec
from tests.helpers import static_capture


def test_propagation_follows_a_rigid_motion(rng):
    # calibrate the wand at one pose, move it rigidly anywhere: sensor 0's pose must carry every
    # sensor to its true pose. Eq. 95 as printed (q ⊗ q⁻¹ = identity) or eq. 98's printed order fail here.
    wand = Simulator(Scene(noise=NoiseSpec.none()), seed=4).wand
    calibration = WandCalibration.from_step(static_capture(wand, [0.45, 0.05, 0.0], R.random(1, rng)[0]))
    body_p = np.array([0.5, 0.0, 0.0]) + 0.05 * rng.standard_normal((100, 3))
    body_q = R.random(100, rng)
    true_p, true_q = wand.sensor_poses(body_p, body_q)
    positions, rotations = calibration.propagate(true_p[:, 0], R.to_matrix(true_q[:, 0]))
    np.testing.assert_allclose(positions, true_p, atol=1e-12)
    assert R.angle_between_matrices(rotations, R.to_matrix(true_q)).max() < 1e-11
    np.testing.assert_allclose(calibration.positions[0], 0, atol=1e-15)
    np.testing.assert_allclose(calibration.rotations[0], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(calibration.lever_arms[1:], np.linalg.norm(wand.body_positions[1:], axis=1),
                               rtol=1e-10)


def test_error_estimate_is_eq_101():
    calibration = WandCalibration(np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0.0]]), np.tile(np.eye(3), (3, 1, 1)),
                                  np.ones(3))
    estimate = calibration.error_estimate(np.array([1e-4]), np.array([2e-3]))
    np.testing.assert_allclose(estimate, [[1e-4, 1e-4 + 0.1 * np.tan(2e-3), 1e-4 + 0.2 * np.tan(2e-3)]])


def test_sweep_mapping_keeps_clean_samples_and_estimates_fields(small_session):
    simulator, session = small_session
    model = FixtureModel.from_session(session)
    mapping = map_sweep(session, model)
    assert mapping.sensor0.converged.mean() > 0.999
    assert mapping.keep.mean() > 0.99
    assert sum(mapping.dropped.values()) == mapping.keep.size - mapping.kept
    # the kept G samples are the scene's field, up to the declared-pose bias and noise: compare in the
    # declared frame, where every sample lives
    r0_true, T_true = simulator.true_cube_frame()
    survey = session.steps["cube_survey"]
    D = R.to_matrix(survey.attrs["declared_quaternion"]) @ T_true.T
    truth = session.truth["wand_sweep"].position @ D.T + (survey.attrs["declared_position"] - D @ r0_true)
    error = np.linalg.norm(mapping.positions - truth, axis=-1)[mapping.keep]
    assert np.median(error) < 2e-4 and np.percentile(error, 99) < 1e-3


def test_gating_drops_perturbed_samples(small_session):
    _, session = small_session
    model = FixtureModel.from_session(session)
    sweep = session.steps["wand_sweep"]
    perturbed = np.zeros(sweep.n_frames, dtype=bool)
    perturbed[::10] = True
    original = sweep.signal.copy()
    try:
        # a disturbance that no pose explains, 1 % of the signal, on sensor 0 of every tenth frame
        rng = np.random.default_rng(0)
        kick = 0.01 * np.sqrt(np.mean(original[:, 0] ** 2, axis=(1, 2)))[:, None, None] * rng.standard_normal(
            (sweep.n_frames, 3, 3))
        sweep.signal[perturbed, 0] += kick[perturbed]
        mapping = map_sweep(session, model)
    finally:
        sweep.signal[:] = original
    dropped = ~mapping.keep.any(axis=1)
    assert dropped[perturbed].mean() > 0.95
    assert dropped[~perturbed].mean() < 0.01
    assert mapping.dropped["residual too high"] + mapping.dropped["estimated error too high"] > 0
    strict = map_sweep(session, model, Gates(max_error=1e-6))
    assert strict.dropped["estimated error too high"] > 0 and strict.kept < mapping.kept


def test_fixture_model_names_missing_steps(small_session):
    _, session = small_session
    partial = Session(steps={"cube_calibration": session.steps["cube_calibration"]})
    with pytest.raises(ValueError, match="ivc collect cube_survey") as refused:
        FixtureModel.from_session(partial)
    assert "wand_sweep" not in str(refused.value)  # the fixtures do not need the sweep
    no_sweep = Session(session.hemisphere, {k: v for k, v in session.steps.items() if k != "wand_sweep"})
    assert FixtureModel.from_session(no_sweep).wand is not None
    assert CubeCalibration.from_step(session.steps["cube_calibration"]).frames.min() > 900


def test_fixtures_cli_reports_calibration_and_truth(small_session, tmp_path):
    import json

    from click.testing import CliRunner

    from ivc import session as session_io
    from ivc.cli import cli

    _, data = small_session
    path = tmp_path / "s.h5"
    session_io.write(data, path)
    result = CliRunner().invoke(cli, ["fixtures", str(path)])
    assert result.exit_code == 0, result.output
    assert "fitted perfect cube edge" in result.output and "wand sensor 7 position" in result.output
    report = json.loads(CliRunner().invoke(cli, ["fixtures", str(path), "--json", "--compare-cubes", "500"]).output)
    assert report["sweep"]["converged_fraction"] > 0.999
    assert report["samples"]["kept"] + sum(report["samples"]["dropped"].values()) == report["samples"]["total"]
    assert report["truth"]["sensor0_position_mm"]["p50"] < 0.3
    assert set(report["cube_choices"]) == {"averaged", "optimised", "ideal"}
    # the averaged vertices are the sensors' real positions: they beat the ideal cube
    choices = report["cube_choices"]
    assert choices["averaged"]["sensor0_position_mm"]["p50"] < choices["ideal"]["sensor0_position_mm"]["p50"]
