import json

import numpy as np
from click.testing import CliRunner

from ivc import __version__, session
from ivc.cli import cli
from tests.helpers import full_session


def test_version_and_help():
    runner = CliRunner()
    result = runner.invoke(cli, ["--version"])
    assert result.exit_code == 0 and __version__ in result.output
    result = runner.invoke(cli, ["--help"])
    assert result.exit_code == 0 and "info" in result.output


def test_info_summarises_and_says_what_is_missing(tmp_path, rng):
    s = full_session(rng)
    del s.steps["wand_sweep"]
    path = tmp_path / "s.h5"
    session.write(s, path)
    result = CliRunner().invoke(cli, ["info", str(path)])
    assert result.exit_code == 0, result.output
    assert "cube_calibration" in result.output and "wand_sweep" in result.output
    assert "ivc collect wand_sweep" in result.output
    data = json.loads(CliRunner().invoke(cli, ["info", str(path), "--json"]).output)
    calibration = data["steps"]["cube_calibration"]
    assert calibration["frames"] == 20 and calibration["sensors"] == 8
    expected = float(np.mean(s.steps["cube_calibration"].valid))
    assert calibration["valid_fraction"] == expected
    assert data["steps"]["check"]["truth"] is True
    assert len(data["missing_for_fit"]) == 1


def test_info_reports_bad_file_cleanly(tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_text("nope")
    result = CliRunner().invoke(cli, ["info", str(bad)])
    assert result.exit_code == 1
    assert "Error: " in result.output and "not an HDF5 file" in result.output
    assert "Traceback" not in result.output
