"""The shipped recordings in sample_data/ still read, correct and predict as sample_data/README.md says."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ivc import lut, rotations
from ivc import session as session_io
from ivc.cli import cli
from ivc.collect.replay import read_csv, write_csv
from ivc.correct.evaluate import evaluate
from ivc.truth import DECLARED_FRAME

SAMPLES = Path(__file__).resolve().parents[1] / "sample_data"
RECORDINGS = SAMPLES / "recordings"
TABLE, CHECK, CHECK_CSV, HEAD_CSV = (RECORDINGS / name for name in (
    "default_room_lut.h5", "default_room_check.h5", "default_room_check.csv", "head_aggressive_120hz.csv"))


def test_shipped_table_corrects_the_shipped_check_poses():
    report = evaluate(lut.read(TABLE), session_io.read(CHECK))
    # one sample is invalid in the recording; five are predicted less precise than the default 0.8 mm limit (three of
    # them only once their residual widens the noise's prediction: 0.23-0.92 mm off)
    assert report["samples"] == 1000 and report["corrected"] >= 994
    assert report["frame"] == DECLARED_FRAME and abs(report["placement_error_mm"] - 1.25) < 0.05
    # Himberg 2010's Table 24 scale: IVC to a fraction of a millimetre, the dipole solution tens of millimetres off
    assert report["ivc"]["position_mm"]["p50"] < 0.2
    assert report["ivc"]["orientation_mrad"]["p50"] < 1.0
    assert report["dipole"]["position_mm"]["p50"] > 30.0


def test_the_shipped_table_is_written_by_this_version_of_the_format():
    # its units text is the one the writer gives today (no reference to a file outside the repository)
    import h5py

    from ivc.table.lookup import FIELD_UNIT

    with h5py.File(TABLE, "r") as h5:
        assert h5.attrs["field_unit"] == FIELD_UNIT
    assert lut.read(TABLE).provenance["parameters"]["method"] == "harmonic"


def test_correct_the_shipped_csv_against_its_truth(tmp_path):
    out = tmp_path / "corrected.csv"
    result = CliRunner().invoke(cli, ["correct", str(TABLE), str(CHECK_CSV), "-o", str(out)])
    assert result.exit_code == 0, result.output
    measured, corrected = read_csv(CHECK_CSV), read_csv(out)
    truth = session_io.read(CHECK).truth["check"]
    frames = measured.n_frames
    ok = corrected.valid_mask[:, 0]
    assert ok.sum() >= frames - 2
    before = np.linalg.norm(measured.position - truth.position[:frames], axis=-1)[:, 0][ok] * 1e3
    after = np.linalg.norm(corrected.position - truth.position[:frames], axis=-1)[:, 0][ok] * 1e3
    # corrected poses are in the declared cube frame, 1.25 mm from the simulator's (sample_data/README.md)
    assert np.median(after) < 2.0 < 30.0 < np.median(before)
    assert "warning" not in result.output


def test_correcting_a_recording_from_elsewhere_says_what_to_check(tmp_path):
    # the head recording was made in free space; with its (free-space) signals they do not fit the room's table.
    # (As reported poses alone it cannot be told from the room's: the pose path corrects those, docs/lut.md.)
    head = read_csv(HEAD_CSV)
    head.signal = head.signal_matrices()
    write_csv(head, tmp_path / "head_signals.csv")
    result = CliRunner().invoke(cli, ["correct", str(TABLE), str(tmp_path / "head_signals.csv"), "-o",
                                      str(tmp_path / "c.csv")])
    assert result.exit_code == 0, result.output
    assert "0 corrected" in result.output
    assert "warning: 100% of the valid samples do not fit the table's field" in result.output
    assert "10x what the table's model error and the signal noise explain" in result.output
    assert "--max-residual LIMIT sets one fixed limit" in result.output  # the library's keyword, said as the flag


@pytest.mark.slow
def test_report_on_the_shipped_table_and_check_poses(tmp_path):
    out = tmp_path / "report"
    result = CliRunner().invoke(cli, ["report", str(CHECK), str(TABLE), "-o", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    numbers = json.loads((out / "report.json").read_text())
    assert numbers["check"]["ivc"]["position_mm"]["p50"] < 0.2 < 30.0 < numbers["check"]["dipole"]["position_mm"]["p50"]
    assert sorted(p.name for p in out.glob("*.png")) == ["error_histograms.png", "error_vs_distance.png",
                                                          "secondary_field.png"]


def test_predict_the_shipped_head_recording(tmp_path):
    out = tmp_path / "ahead.csv"
    result = CliRunner().invoke(cli, ["predict", str(HEAD_CSV), "--filter", "mmdq2", "--horizon", "50ms",
                                      "-o", str(out)])
    assert result.exit_code == 0, result.output
    measured, predicted = read_csv(HEAD_CSV).quaternion[:, 0], read_csv(out).quaternion[:, 0]
    ahead = round(0.05 * 120)
    later = measured[ahead:]
    error = rotations.angle_between(predicted[:-ahead], later)[60:]  # after the filter has settled
    none = rotations.angle_between(measured[:-ahead], later)[60:]
    assert error.mean() < none.mean() / 3


@pytest.mark.slow
def test_the_maker_writes_a_head_recording_and_never_replaces_one(tmp_path):
    args = [sys.executable, str(SAMPLES / "make.py"), "--only", "head", "--out", str(tmp_path)]
    subprocess.run(args, check=True, capture_output=True)
    step = read_csv(tmp_path / "head_aggressive_120hz.csv")
    shipped = read_csv(HEAD_CSV)
    assert step.quaternion.shape == shipped.quaternion.shape
    assert step.sample_rate_hz == shipped.sample_rate_hz == 120.0
    before = (tmp_path / "head_aggressive_120hz.csv").read_bytes()
    again = subprocess.run(args, capture_output=True, text=True)
    assert again.returncode != 0 and "not replaced" in again.stderr
    assert (tmp_path / "head_aggressive_120hz.csv").read_bytes() == before


def test_info_on_a_recording_csv_and_evaluate_refuses_one():
    result = CliRunner().invoke(cli, ["info", str(CHECK_CSV), "--json"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.output)
    step = read_csv(CHECK_CSV)
    assert info["frames"] == step.n_frames == 240 and info["sensors"] == ["check0"]
    assert info["sample_rate_hz"] == 240.0 and info["data"] == "signal+pose"
    text = CliRunner().invoke(cli, ["info", str(HEAD_CSV)]).output
    assert "1200 frames x 1 sensors (head)" in text and "data: pose" in text
    refused = CliRunner().invoke(cli, ["evaluate", str(TABLE), str(CHECK_CSV)])
    assert refused.exit_code != 0 and "holds no true poses" in refused.output and "Traceback" not in refused.output
    # anything else that reads a session says what a CSV is and how to make a session of it
    refused = CliRunner().invoke(cli, ["report", str(CHECK_CSV), str(TABLE), "-o", "unused"])
    assert refused.exit_code != 0 and "a recording CSV, not an ivc session file" in refused.output
