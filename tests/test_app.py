"""The app layer (ivc.correct_file, ivc.predict_file) against the library's stages called directly, the corrected
datasets of session/io.py, and the CLI saying the library's keywords as its flags."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import ivc
from ivc import lut
from ivc import session as session_io
from ivc.cli import cli
from ivc.cli.flags import cli_words
from ivc.collect.replay import read_csv, write_csv
from ivc.correct import Corrector
from ivc.errors import OptionsError
from ivc.predict import make

RECORDINGS = Path(__file__).resolve().parents[1] / "sample_data" / "recordings"
TABLE, CHECK, CHECK_CSV, HEAD_CSV = (RECORDINGS / name for name in (
    "default_room_lut.h5", "default_room_check.h5", "default_room_check.csv", "head_aggressive_120hz.csv"))


def test_correct_file_on_a_csv_is_the_corrector_on_its_signals(tmp_path):
    messages = []
    out = tmp_path / "corrected.csv"
    result = ivc.correct_file(TABLE, CHECK_CSV, out, ivc.CorrectOptions(max_precision=0.2e-3),
                              report=lambda kind, text: messages.append((kind, text)))
    step = read_csv(CHECK_CSV)
    direct = Corrector(lut.read(TABLE), precision=True, max_precision=0.2e-3).batch(step.signal, step.valid_mask)
    got = result.corrections[CHECK_CSV.name]
    np.testing.assert_array_equal(got.flags, direct.flags)
    np.testing.assert_array_equal(got.position, direct.position)
    np.testing.assert_array_equal(got.precision, direct.precision)
    assert 0 < np.sum(direct.flags == 16) < direct.flags.size  # the precision limit flags some poses, not all
    written = read_csv(out)
    np.testing.assert_array_equal(written.position, direct.position)  # 17 significant digits: exact
    np.testing.assert_array_equal(written.valid_mask, direct.flags == 0)
    assert written.signal is None and result.output == out
    assert ("info", "precision gate: poses predicted less precise than 0.2 mm RMS are flagged (16)") in messages
    assert any(kind == "info" and text.startswith(f"{CHECK_CSV.name}: 240 samples") for kind, text in messages)


def test_correct_file_on_a_session_writes_the_corrected_datasets_session_io_reads(tmp_path):
    out = tmp_path / "corrected.h5"
    result = ivc.correct_file(TABLE, CHECK, out, ivc.CorrectOptions(steps=["check"], precision=True))
    stored = session_io.read_corrections(out)
    assert set(stored) == {"check"} == set(result.corrections)
    for key in ("flags", "residual", "precision", "orientation_precision"):
        np.testing.assert_array_equal(getattr(stored["check"], key), getattr(result.corrections["check"], key))
    corrected = session_io.read(out)
    assert corrected.attrs["corrected_with"] == str(TABLE) and len(corrected.attrs["lut_sha256"]) == 64
    assert corrected.steps["check"].attrs["corrected_with"] == str(TABLE)
    np.testing.assert_array_equal(corrected.steps["check"].position, result.corrections["check"].position)
    data = session_io.read(CHECK)
    direct = Corrector(lut.read(TABLE), data.hemisphere).batch(data.steps["check"].signal,
                                                               data.steps["check"].valid_mask)
    np.testing.assert_array_equal(stored["check"].flags, direct.flags)
    # one sample is invalid in the recording, five are predicted less precise than the default 0.8 mm (three of them
    # only once their residual widens the noise's prediction)
    assert result.trusted == int(np.sum(direct.flags == 0)) == 994
    assert np.sum(direct.flags == 16) == 5
    with pytest.raises(FileExistsError, match="overwrite=True"):
        ivc.correct_file(TABLE, CHECK, out)


def test_session_io_refuses_corrections_of_a_step_it_does_not_write(tmp_path):
    data = session_io.read(CHECK)
    flags = np.zeros(data.steps["check"].valid_mask.shape, dtype=np.uint8)
    with pytest.raises(ivc.SessionError, match="wand_sweep"):
        session_io.write(data, tmp_path / "x.h5", corrections={"wand_sweep": session_io.StepCorrection(flags, flags)})
    assert session_io.read_corrections(CHECK) == {} and not (tmp_path / "x.h5").exists()


def test_options_that_do_not_fit_are_refused_in_keywords_and_said_as_flags_by_the_cli(tmp_path):
    with pytest.raises(OptionsError, match="give predictor=NAME"):
        ivc.correct_file(TABLE, CHECK_CSV, tmp_path / "a.csv", ivc.CorrectOptions(tune=True))
    with pytest.raises(OptionsError, match=r"output=FILE\.csv"):
        ivc.correct_file(TABLE, CHECK_CSV, tmp_path / "a.h5")
    assert not (tmp_path / "a.csv").exists() and not (tmp_path / "a.h5").exists()
    runner = CliRunner()
    refused = runner.invoke(cli, ["correct", str(TABLE), str(CHECK_CSV), "-o", str(tmp_path / "a.h5")])
    assert refused.exit_code == 2 and "-o FILE.csv" in refused.output and "output=" not in refused.output
    (tmp_path / "b.csv").write_text("")
    refused = runner.invoke(cli, ["correct", str(TABLE), str(CHECK_CSV), "-o", str(tmp_path / "b.csv")])
    assert refused.exit_code == 1 and "pass --force to replace it" in refused.output, refused.output


def test_predict_file_is_the_predictor_on_the_recording(tmp_path):
    out = tmp_path / "ahead.csv"
    result = ivc.predict_file(HEAD_CSV, out, ivc.PredictOptions(filter="mmdq2", horizon=0.05))
    step = read_csv(HEAD_CSV)
    direct = make("mmdq2", step.sample_rate_hz).predict(step.quaternion, 0.05, step.valid_mask, time=step.time)[0]
    direct = np.where(np.all(np.isfinite(direct), axis=-1, keepdims=True), direct, step.quaternion)
    np.testing.assert_array_equal(result.steps[HEAD_CSV.name].quaternion, direct)
    np.testing.assert_array_equal(read_csv(out).quaternion, direct)
    np.testing.assert_array_equal(read_csv(out).position, step.position)  # positions as they were


def test_predict_file_on_a_session_keeps_every_step_and_names_the_filter(tmp_path):
    out = tmp_path / "ahead.h5"
    result = ivc.predict_file(CHECK, out, ivc.PredictOptions(filter="poly1", horizon=0.02, steps=["check"]))
    predicted = session_io.read(out)
    assert set(predicted.steps) == {"check"} == set(result.steps)
    assert predicted.attrs["predicted_with"] == "poly1" and predicted.attrs["prediction_horizon_s"] == 0.02
    assert predicted.steps["check"].signal is None


def test_cli_words_say_keywords_as_the_commands_flags():
    assert cli_words("x.h5 exists; pass overwrite=True to replace it") == "x.h5 exists; pass --force to replace it"
    assert cli_words("tune_from=/data/a.csv:\ntuning") == "--tune-from /data/a.csv:\ntuning"
    assert cli_words("the live stream (rate_hz=240)", "correct") == "the live stream (--rate-hz 240)"
    assert cli_words("pass rate_hz=HZ", "predict") == "pass --rate HZ"
    assert cli_words("or raise the gate (max_residual=)", "fit") == "or raise the gate (--max-residual)"
    # a path or an unknown keyword stays as it is
    assert cli_words("/tmp/overwrite=True/x and colour=red") == "/tmp/overwrite=True/x and colour=red"


def test_solver_is_the_flag_and_tracker_its_hidden_alias(tmp_path):
    runner = CliRunner()
    shown = runner.invoke(cli, ["correct", "--help"]).output
    assert "--solver [closed-form|least-squares]" in shown and "--tracker " not in shown
    step = read_csv(CHECK_CSV)
    poses = tmp_path / "poses.csv"
    write_csv(replace(step, signal=None, time=step.time[:40], position=step.position[:40],
                      quaternion=step.quaternion[:40], valid=step.valid_mask[:40]), poses)
    outputs = []
    for flag in ("--solver", "--tracker"):
        outputs.append(tmp_path / f"out{flag}.csv")
        result = runner.invoke(cli, ["correct", str(TABLE), str(poses), "-o", str(outputs[-1]), flag, "least-squares"])
        assert result.exit_code == 0, result.output
    assert outputs[0].read_bytes() == outputs[1].read_bytes()
    direct = ivc.PoseCorrector(lut.read(TABLE), solver="least-squares").batch(
        step.position[:40], step.quaternion[:40], step.valid_mask[:40])
    np.testing.assert_array_equal(read_csv(outputs[0]).position, direct.position)


def test_live_corrector_refuses_what_a_stream_cannot_do_before_it_connects(tmp_path):
    url = "igtl://127.0.0.1:1"
    with pytest.raises(OptionsError, match="tune=True needs the whole recording"):
        ivc.live_corrector(TABLE, url, ivc.CorrectOptions(predictor="mmdq2", tune=True))
    with pytest.raises(OptionsError, match="tracker_model=FILE"):
        ivc.live_corrector(TABLE, url, ivc.CorrectOptions(tracker_model=tmp_path / "t.json"))
    with pytest.raises(OptionsError, match=r"recording at 120 Hz, the live stream \(rate_hz=240\)"):
        ivc.live_corrector(TABLE, url, ivc.CorrectOptions(predictor="mmdq2", tune_from=HEAD_CSV),
                           ivc.LiveOptions(rate_hz=240.0))
    with pytest.raises(OptionsError, match="length_unit='furlong'"):
        ivc.live_corrector(TABLE, url, live=ivc.LiveOptions(length_unit="furlong"))


@pytest.mark.parametrize("scale, hemisphere", [(1000.0, None), (1.0, "-x")])
def test_signals_in_another_scale_or_hemisphere_are_not_sent_to_sweep_the_room(scale, hemisphere):
    """Signals x1000 or the wrong hemisphere land outside the map and off its field: the advice names the scale,
    the units and the hemisphere, not more sweeping (issue 41's messages)."""
    from ivc.app.correct import correction_advice
    from ivc.collect.replay import read_csv

    step = read_csv(CHECK_CSV)
    out = Corrector(lut.read(TABLE), hemisphere).batch(step.signal * scale, step.valid_mask)
    advice = correction_advice(out, 1e-3)
    assert "scale" in advice and "hemisphere" in advice and "sweep the wand there" not in advice
