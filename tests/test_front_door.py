"""The library's front door: the whole job through ``import ivc`` alone, and the CLI's error policy."""

import numpy as np
import pytest
from click.testing import CliRunner

PLATE_SCENE = """
name = "plate"
hemisphere = "+x"
check_radius_mm = 70
[[conductor]]
shape = "plate"
size = [1.0, 1.0]
position = [0.5, 0.0, -0.35]
material = "aluminium"
resolution_mm = 80
"""
FRAMES = {"cube_calibration": 1000, "cube_survey": 200, "wand_calibration": 200, "wand_sweep": 10_000, "check": 300}


@pytest.mark.slow
def test_the_whole_job_through_import_ivc_alone(tmp_path):
    import ivc

    (tmp_path / "plate.toml").write_text(PLATE_SCENE)
    simulator = ivc.Simulator(ivc.load_scene(str(tmp_path / "plate.toml")), seed=9)
    ivc.write_session(simulator.protocol(FRAMES), tmp_path / "room.h5")
    session = ivc.read_session(tmp_path / "room.h5")
    assert list(session.steps) == list(FRAMES) and session.steps["wand_sweep"].n_frames == 10_000

    ivc.write_lut(ivc.fit_lut(session, ivc.FitOptions()), tmp_path / "room_lut.h5")
    table = ivc.read_lut(tmp_path / "room_lut.h5")
    assert isinstance(table, ivc.LookupTable)

    check, truth = session.steps["check"], session.truth["check"]
    corrected = ivc.Corrector(table).batch(check.signal_matrices(), check.valid_mask)
    ok = corrected.ok
    assert ok.mean() > 0.9
    error = np.linalg.norm(corrected.position - truth.position, axis=-1)[ok]
    raw = np.linalg.norm(check.poses(session.hemisphere)[0] - truth.position, axis=-1)[ok]
    assert np.median(error) < 0.2 * np.median(raw)

    report = ivc.evaluate(table, session)  # in the declared cube frame, which removes the placement offset
    assert report["corrected"] == ok.sum()
    declared_frame_p50 = report["ivc"]["position_mm"]["p50"]
    assert declared_frame_p50 < min(1000 * np.median(error), 0.01 * report["dipole"]["position_mm"]["p50"])

    ahead = ivc.predict.make("dqekf-cv", check.sample_rate_hz).predict(corrected.quaternion, 0.05)
    assert ahead.shape == (1, *corrected.quaternion.shape)
    assert np.isfinite(ahead[0, 10:][ok[10:]]).all()

    written = ivc.export_table(table, "vti", tmp_path / "room.vti")
    assert written.exists() and written.stat().st_size > 0


def test_protocol_steps_equal_steps_simulated_alone():
    import ivc

    simulator = ivc.Simulator(ivc.Scene(), seed=3)
    seen = []
    session = simulator.protocol({"wand_sweep": 300, "check": 50}, steps=("wand_calibration", "wand_sweep", "check"),
                                 on_step=lambda name, step, s: seen.append((name, step.n_frames, len(s.steps))))
    assert seen == [("wand_calibration", 500, 1), ("wand_sweep", 300, 2), ("check", 50, 3)]
    alone, truth = simulator.step("wand_sweep", 300)
    np.testing.assert_array_equal(session.steps["wand_sweep"].signal, alone.signal)
    np.testing.assert_array_equal(session.truth["wand_sweep"].position, truth.position)
    assert session.attrs == {"scene": "free space", "seed": 3}
    with pytest.raises(ivc.InputError, match="unknown step 'sweep'"):
        simulator.protocol({"sweep": 10})


def test_every_public_name_resolves_and_every_error_is_an_ivc_error():
    import importlib
    import types

    import ivc

    for package in ("app", "cli", "collect", "correct", "demo", "dipole", "export", "fixtures", "live", "lut", "pose",
                    "predict", "report", "session", "sim"):
        importlib.import_module(f"ivc.{package}")  # importing a subpackage must not shadow a front-door name
    for name in ivc.__all__:
        value = getattr(ivc, name)
        assert value is not None, name
    for name in ("read_session", "write_session", "replay", "load_scene", "fit_lut", "read_lut", "write_lut",
                 "evaluate", "export_table", "correct_file", "predict_file", "live_corrector"):
        assert callable(getattr(ivc, name)) and not isinstance(getattr(ivc, name), types.ModuleType), name
    assert set(ivc.__all__) <= set(dir(ivc))
    with pytest.raises(AttributeError):
        ivc.no_such_name  # noqa: B018
    from ivc import errors

    for name in errors.__all__:
        error = getattr(errors, name)
        assert issubclass(error, ivc.IvcError) and (error is ivc.IvcError or issubclass(error, ValueError)), name
    assert not issubclass(ivc.LutError, ivc.SessionError)  # a table error is not a session error


def test_a_user_error_is_one_line_and_an_internal_bug_keeps_its_traceback(tmp_path, monkeypatch):
    from ivc.cli import cli

    runner = CliRunner()
    missing = runner.invoke(cli, ["info", str(tmp_path / "nothing.h5")])
    assert missing.exit_code != 0 and isinstance(missing.exception, SystemExit)
    assert missing.output.strip().count("\n") == 0 and "Error:" in missing.output and "Traceback" not in missing.output

    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not an hdf5 file")
    refused = runner.invoke(cli, ["info", str(bad)])
    assert isinstance(refused.exception, SystemExit) and "Error:" in refused.output

    import ivc.cli.info as info

    def broken(*args, **kwargs):
        raise KeyError("an internal bug")

    monkeypatch.setattr(info, "_is_table", broken)
    crashed = runner.invoke(cli, ["info", str(bad)])
    assert isinstance(crashed.exception, KeyError)  # not turned into a one-line "Error:"

    def user_error(*args, **kwargs):
        from ivc.errors import SessionError

        raise SessionError("a user error")

    monkeypatch.setattr(info, "_is_table", user_error)
    one_line = runner.invoke(cli, ["info", str(bad)])
    assert one_line.output.strip() == "Error: a user error"
    debug = runner.invoke(cli, ["--debug", "info", str(bad)])
    assert type(debug.exception).__name__ == "SessionError"  # --debug shows the traceback of user errors too
