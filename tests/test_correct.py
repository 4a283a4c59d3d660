"""Correction with a look-up table: exact recovery, flags, streaming, quaternions, and the CLI."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from ivc import dipole, rotations
from ivc import session as session_io
from ivc.cli import cli
from ivc.collect.replay import write_csv
from ivc.correct import HIGH_RESIDUAL, INVALID_INPUT, OUTSIDE, Corrector
from ivc.correct.kernels import quaternion_of
from tests.helpers import distorted, quadratic_field


def test_correction_recovers_exact_poses_when_the_table_is_the_true_field(exact_table, rng):
    r, T, S = distorted(rng, 2000)
    assert np.median(np.linalg.norm(dipole.closed_form_pose(S)[0] - r, axis=1)) > 5e-3  # a real distortion
    out = Corrector(exact_table).batch(S)
    assert np.all(out.flags == 0)
    assert np.abs(out.position - r).max() < 1e-9
    assert rotations.angle_between(out.quaternion, rotations.from_matrix(T)).max() < 1e-8
    assert np.all(out.residual < 1e-8)


def test_streaming_matches_batch_and_warm_starts(exact_table, rng):
    r, T, S = distorted(rng, 400)
    corrector = Corrector(exact_table)
    batch = corrector.batch(S)
    frames = S.reshape(100, 4, 3, 3)  # 4 sensors, 100 frames
    streamed = [corrector.update(frame, sensors=["a", "b", "c", "d"]) for frame in frames]
    np.testing.assert_allclose(np.concatenate([s.position for s in streamed]), batch.position, atol=1e-9)
    assert all(np.all(s.flags == 0) for s in streamed)
    corrector.reset()
    assert corrector.update(frames[0], ["a", "b", "c", "d"]).flags.tolist() == [0, 0, 0, 0]


def test_points_outside_the_map_and_bad_input_are_flagged_never_silently_returned(exact_table, rng):
    r, T, S = distorted(rng, 3)
    far = np.array([0.9, 0.3, 0.0])  # outside the grid
    S_far = dipole.signal(far, T[0], quadratic_field(far[None])[0])
    S_all = np.stack([S[0], S_far, np.full((3, 3), np.nan), S[1]])
    out = Corrector(exact_table).batch(S_all, valid=np.array([True, True, True, False]))
    assert out.flags.shape == out.residual.shape == (4,) and out.position.shape == (4, 3)
    assert out.flags[0] == 0
    assert out.flags[1] & OUTSIDE
    assert out.flags[2] == INVALID_INPUT and np.all(np.isnan(out.position[2]))
    assert out.flags[3] == INVALID_INPUT
    # a signal no pose explains is flagged by its residual
    kicked = S[2] + 0.05 * np.abs(S[2]).max() * np.array([[1, -1, 0], [0, 1, 1], [1, 0, -1.0]])
    assert Corrector(exact_table).batch(kicked[None]).flags[0] & HIGH_RESIDUAL


def test_pose_only_input_is_rebuilt_into_signals(exact_table, rng):
    r, T, S = distorted(rng, 50)
    p, R = dipole.closed_form_pose(S)  # what a commercial tracker reports
    q = rotations.from_matrix(R)
    corrector = Corrector(exact_table)
    from_poses = corrector.batch_poses(p, q)
    from_signal = corrector.batch(dipole.signal_from_pose(p, q))
    np.testing.assert_array_equal(from_poses.position, from_signal.position)


def test_compiled_quaternion_equals_the_reference(rng):
    T = rotations.to_matrix(np.concatenate([rotations.random(500, rng), [[0, 1, 0, 0], [0, 0, -1, 1] / np.sqrt(2)],
                                            [[1, 0, 0, 0]]]))
    q = np.empty((len(T), 4))
    for n in range(len(T)):
        quaternion_of.py_func(T[n], q[n])
    np.testing.assert_allclose(q, rotations.from_matrix(T), atol=1e-15)


@pytest.mark.slow
def test_cli_fit_correct_evaluate(small_session, tmp_path):
    _, session = small_session
    session_file, table_file = tmp_path / "s.h5", tmp_path / "lut.h5"
    session_io.write(session, session_file)
    runner = CliRunner()
    result = runner.invoke(cli, ["fit", str(session_file), "-o", str(table_file), "--min-support", "5"])
    assert result.exit_code == 0, result.output
    assert "cross-validation RMS" in result.output and "wand samples kept" in result.output
    assert "Signal noise" in result.output  # measured on the static steps, for --precision
    again = runner.invoke(cli, ["fit", str(session_file), "-o", str(table_file)])
    assert again.exit_code != 0 and "exists" in again.output

    described = runner.invoke(cli, ["info", str(table_file)])
    assert described.exit_code == 0 and "look-up table" in described.output and "nodes mapped" in described.output

    result = runner.invoke(cli, ["evaluate", str(table_file), str(session_file), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["ivc"]["position_mm"]["p50"] < 0.2 * report["dipole"]["position_mm"]["p50"]
    text = runner.invoke(cli, ["evaluate", str(table_file), str(session_file)]).output
    assert "IVC position" in text and "dipole position (uncorrected)" in text and "99%" in text
    assert "predicted precision" in text and "error / predicted precision" in text
    # a short sweep: the map adds error of its own above the noise (ratio 1.9 here), never far below it
    assert 0.5 < report["predicted_precision"]["error_over_predicted_median"] < 5

    out_file = tmp_path / "corrected.h5"
    result = runner.invoke(cli, ["correct", str(table_file), str(session_file), "-o", str(out_file)])
    assert result.exit_code == 0, result.output
    corrected = session_io.read(out_file)
    assert set(corrected.steps) == {"cube_survey", "wand_sweep", "check"}
    import h5py
    with h5py.File(out_file) as h5:
        flags = h5["steps/check/flags"][()]
    assert flags.shape == (300, 1)
    ok = flags == 0
    check_error = np.linalg.norm(corrected.steps["check"].position - session.truth["check"].position, axis=-1)
    assert np.median(check_error[ok]) < 0.01
    precise = runner.invoke(cli, ["correct", str(table_file), str(session_file), "-o", str(tmp_path / "p.h5"),
                                  "--step", "check", "--max-precision", "0.05"])
    assert precise.exit_code == 0, precise.output
    with h5py.File(tmp_path / "p.h5") as h5:
        predicted, flagged = h5["steps/check/precision"][()], h5["steps/check/flags"][()]
    assert h5py and np.all(((flagged & 16) != 0) == (predicted > 5e-5))
    refused = runner.invoke(cli, ["correct", str(table_file), str(session_file), "-o", str(session_file), "--force"])
    assert refused.exit_code != 0 and "never overwritten" in refused.output

    csv_in, csv_out = tmp_path / "check.csv", tmp_path / "check_corrected.csv"
    write_csv(session.steps["check"], csv_in)
    result = runner.invoke(cli, ["correct", str(table_file), str(csv_in), "-o", str(csv_out)])
    assert result.exit_code == 0, result.output
    lines = csv_out.read_text().splitlines()
    assert lines[0].endswith("valid,flags,residual,precision_mm,orientation_precision_mrad") and len(lines) == 301
    x_csv = np.array([float(line.split(",")[2]) for line in lines[1:]])
    np.testing.assert_allclose(x_csv, corrected.steps["check"].position[:, 0, 0], atol=1e-12)

    # correction chained with prediction: horizon 0 leaves the trusted orientations as corrected
    same, ahead = tmp_path / "p0.h5", tmp_path / "p50.h5"
    for path, horizon in ((same, "0ms"), (ahead, "50ms")):
        result = runner.invoke(cli, ["correct", str(table_file), str(session_file), "-o", str(path), "--step", "check",
                                     "--predict", "mmdq2", "--horizon", horizon])
        assert result.exit_code == 0, result.output
    q0 = session_io.read(same).steps["check"].quaternion
    q50 = session_io.read(ahead).steps["check"].quaternion
    q_corr = corrected.steps["check"].quaternion
    assert np.allclose(np.abs(np.sum(q0[ok] * q_corr[ok], axis=-1)), 1.0, atol=1e-12)
    assert not np.allclose(q50[ok], q_corr[ok])
    assert session_io.read(ahead).steps["check"].attrs["predicted_with"] == "mmdq2"

    # --tune tunes to the trusted samples only: here 20 % of them, in stretches too short, so it is refused
    tuned = tmp_path / "tuned.h5"
    refused = runner.invoke(cli, ["correct", str(table_file), str(session_file), "-o", str(tuned), "--step", "check",
                                  "--predict", "q-ekf", "--tune"])
    assert refused.exit_code != 0 and "no gap-free stretch" in refused.output and not tuned.exists()
    for args, message in ((["--tune"], "give --predict NAME"),
                          (["--tune", "--predict", "mmdq2", "--live", "igtl://127.0.0.1:1"], "live stream")):
        refused = runner.invoke(cli, ["correct", str(table_file), *args])
        assert refused.exit_code != 0 and message in refused.output


def test_correct_advice_names_the_dominant_flag():
    from ivc.app.correct import correction_advice
    from ivc.correct.solver import HIGH_RESIDUAL, INVALID_INPUT, NOT_CONVERGED, OUTSIDE, Correction

    def out(flags):
        flags = np.array(flags, dtype=np.uint8)
        n = len(flags)
        return Correction(np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)), flags, np.full(n, 0.01), np.ones(n))

    assert correction_advice(out([0, 0, OUTSIDE, INVALID_INPUT]), 1e-3) is None  # most valid samples trusted
    assert "outside the table's mapped volume" in correction_advice(out([OUTSIDE, OUTSIDE, 0, INVALID_INPUT]), 1e-3)
    assert "67% of the valid samples" in correction_advice(out([OUTSIDE, OUTSIDE, 0, INVALID_INPUT]), 1e-3)
    high = out([HIGH_RESIDUAL, HIGH_RESIDUAL | OUTSIDE, HIGH_RESIDUAL])
    assert "median residual 0.01" in correction_advice(high, 1e-3)
    assert "did not converge" in correction_advice(out([NOT_CONVERGED, NOT_CONVERGED, 0]), 1e-3)
    assert "invalid" in correction_advice(out([INVALID_INPUT, INVALID_INPUT]), 1e-3)
