"""Issue 41, "nothing lost, nothing silently wrong", at the command line: plots never replace a file without --force
and are checked before the work; ivc's corrected outputs are recognised by content and not corrected twice; files
are told apart by content; a tracker model checked on points it was not calibrated for says so; rates, seeds and
ports out of range are refused before any work; a full disk during an ITK export is one line."""

import errno
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ivc import session as session_io
from ivc.app.inputs import (
    FOREIGN,
    PLUS,
    RECORDING,
    RIG,
    SESSION,
    TABLE,
    TRACKER,
    check_rate,
    corrected_by,
    file_kind,
)
from ivc.cli import cli
from ivc.errors import OptionsError

SAMPLES = Path(__file__).resolve().parents[1] / "sample_data" / "recordings"
LUT, CHECK_H5, CHECK_CSV = SAMPLES / "default_room_lut.h5", SAMPLES / "default_room_check.h5", \
    SAMPLES / "default_room_check.csv"
HEAD = SAMPLES / "head_aggressive_120hz.csv"


def _one_line_error(result, code=(1, 2)):
    assert result.exit_code in code, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert "Traceback" not in result.output
    return result.output


def _short_head(tmp_path) -> Path:
    """The first 2 s of the head-motion sample: enough for --evaluate, quick."""
    lines = HEAD.read_text().splitlines()
    path = tmp_path / "head.csv"
    path.write_text("\n".join(lines[:241]) + "\n")
    return path


# ---- item 2: plots --------------------------------------------------------------------------------------------------

def test_evaluate_plot_never_replaces_a_file_without_force(tmp_path):
    head = _short_head(tmp_path)
    notes = tmp_path / "notes.svg"
    notes.write_text("my notes")
    args = ["predict", str(head), "--evaluate", "--filter", "poly1", "--horizon", "25ms", "--plot", str(notes)]
    out = _one_line_error(CliRunner().invoke(cli, args))
    assert "exists" in out and "--force" in out and notes.read_text() == "my notes"
    result = CliRunner().invoke(cli, [*args, "--force"])
    assert result.exit_code == 0, result.output
    assert notes.read_text().lstrip().startswith("<?xml") and "<svg" in notes.read_text()  # an SVG, as named
    assert sorted(p.name for p in tmp_path.iterdir()) == ["head.csv", "notes.svg"]  # no temporary file left


def test_benchmark_plot_never_replaces_a_file_without_force(tmp_path):
    notes = tmp_path / "notes.png"
    notes.write_bytes(b"not mine to lose")
    out = _one_line_error(CliRunner().invoke(cli, ["predict", "--benchmark", "--frames", "1000", "--motion",
                                                   "aggressive", "--filter", "none", "--plot", str(notes)]))
    assert "exists" in out and notes.read_bytes() == b"not mine to lose"


@pytest.mark.parametrize("mode", [["--evaluate"], ["--benchmark", "--frames", "1000"]])
def test_a_plot_format_matplotlib_cannot_write_is_refused_before_the_work(tmp_path, mode, monkeypatch):
    """`--plot x.csv` raised matplotlib's ValueError after the whole evaluation."""
    import ivc.cli.predict as predict_cli

    def no_work(*args, **kwargs):
        raise AssertionError("the work started")

    monkeypatch.setattr(predict_cli, "run_evaluation", no_work)
    monkeypatch.setattr(predict_cli, "run_benchmark", no_work)
    head = _short_head(tmp_path)
    out = _one_line_error(CliRunner().invoke(cli, ["predict", str(head), *mode, "--plot", str(tmp_path / "x.csv")]))
    assert "--plot" in out and "'.csv'" in out and "png" in out
    assert not (tmp_path / "x.csv").exists()
    out = _one_line_error(CliRunner().invoke(cli, ["predict", str(head), "--plot", str(tmp_path / "x.png"),
                                                   "-o", str(tmp_path / "o.csv")]))
    assert "--evaluate or --benchmark" in out


def test_an_interrupted_plot_leaves_the_old_file_whole(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    from ivc.app.paths import atomic_figure

    path = tmp_path / "scores.pdf"
    path.write_bytes(b"old figure")

    def interrupted(self, *args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(Figure, "savefig", interrupted)
    with pytest.raises(KeyboardInterrupt), atomic_figure(path) as handle:
        Figure().savefig(handle)
    assert path.read_bytes() == b"old figure" and [p.name for p in tmp_path.iterdir()] == ["scores.pdf"]


# ---- item 4: outputs say what they are -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def corrected(tmp_path_factory):
    """The sample check CSV and session corrected once, and a pose-only corrected session."""
    folder = tmp_path_factory.mktemp("corrected")
    for source, name in ((CHECK_CSV, "once.csv"), (CHECK_H5, "once.h5")):
        result = CliRunner().invoke(cli, ["correct", str(LUT), str(source), "-o", str(folder / name)])
        assert result.exit_code == 0, result.output
    data = session_io.read(folder / "once.h5")
    for step in data.steps.values():
        step.signal = None
    session_io.write(data, folder / "poses_once.h5")
    return folder


def test_kinds_are_told_apart_by_content_not_extension(tmp_path, corrected):
    named_wrongly = {TABLE: (LUT, "table.csv"), SESSION: (CHECK_H5, "session.csv"), RECORDING: (CHECK_CSV, "rec.h5")}
    for kind, (source, name) in named_wrongly.items():
        assert file_kind(source) == kind
        (tmp_path / name).write_bytes(source.read_bytes())
        assert file_kind(tmp_path / name) == kind
    assert file_kind(HEAD) == RECORDING
    rig = tmp_path / "rig.txt"
    rig.write_text("x,y,z,qw,qx,qy,qz," + ",".join(f"s{i}{j}" for i in range(3) for j in range(3)) + "\n")
    assert file_kind(rig) == RIG
    tracker = tmp_path / "tracker.h5"
    tracker.write_text(json.dumps({"format": "ivc-tracker", "version": 1}))
    assert file_kind(tracker) == TRACKER
    liberty = tmp_path / "liberty.csv"
    liberty.write_text("Time,w1,x1,y1,z1,loc1_x,loc1_y,loc1_z\n0,1,0,0,0,1,2,3\n")
    assert file_kind(liberty) == FOREIGN
    plus = tmp_path / "x.igs.mha"
    plus.write_text("ObjectType = Image\nNDims = 3\n")
    assert file_kind(plus) == PLUS
    assert file_kind(tmp_path / "absent.h5") is None


def test_corrected_outputs_are_recognised(corrected):
    assert corrected_by(CHECK_CSV) is None and corrected_by(CHECK_H5) is None and corrected_by(LUT) is None
    assert "flags, residual" in corrected_by(corrected / "once.csv")
    assert "corrected_with" in corrected_by(corrected / "once.h5")
    assert "corrected_with" in corrected_by(corrected / "poses_once.h5")


def test_a_corrected_plus_sequence_is_recognised(tmp_path):
    from ivc.collect.plus import read_plus, write_plus

    path = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "plus" / "Prostate10_tracker.igs.mha"
    if not path.exists():
        pytest.skip(f"{path} is not here (shared data beside the repository)")
    sequence = read_plus(path)
    out = tmp_path / "corrected.igs.mha"
    write_plus(sequence, out, {"{tool}To{tracker}Ivc": (sequence.step.position, sequence.step.quaternion, None)})
    assert file_kind(path) == file_kind(out) == PLUS
    assert corrected_by(path) is None and "IvcTransform" in corrected_by(out)


@pytest.mark.parametrize("name", ["once.csv", "once.h5", "poses_once.h5"])
def test_correct_refuses_its_own_output_unless_allowed(corrected, tmp_path, name):
    """A corrected CSV fed back moved positions another 73 mm median, 203 of 240 trusted (issue 41)."""
    out = tmp_path / f"twice{Path(name).suffix}"
    text = _one_line_error(CliRunner().invoke(cli, ["correct", str(LUT), str(corrected / name), "-o", str(out)]))
    assert "corrected output" in text and "--allow-corrected" in text and "twice" in text and not out.exists()
    import ivc

    with pytest.raises(OptionsError, match="allow_corrected=True"):
        ivc.correct_file(LUT, corrected / name, out)
    result = CliRunner().invoke(cli, ["correct", str(LUT), str(corrected / name), "-o", str(out),
                                      "--allow-corrected"])
    assert result.exit_code == 0, result.output
    assert out.exists()


def test_evaluate_refuses_corrected_reported_poses_unless_allowed(corrected):
    """A corrected pose-only session gave '84 % trusted at 68 mm': its corrected poses corrected again."""
    path = corrected / "poses_once.h5"
    text = _one_line_error(CliRunner().invoke(cli, ["evaluate", str(LUT), str(path)]))
    assert "corrected output" in text and "--allow-corrected" in text
    result = CliRunner().invoke(cli, ["evaluate", str(LUT), str(path), "--allow-corrected", "--json"])
    assert result.exit_code == 0, result.output
    # with signals the correction starts from them, not from the corrected poses: nothing is corrected twice
    result = CliRunner().invoke(cli, ["evaluate", str(LUT), str(corrected / "once.h5"), "--json"])
    assert result.exit_code == 0, result.output


def test_files_in_the_wrong_place_are_named_for_what_they_are(tmp_path):
    text = _one_line_error(CliRunner().invoke(cli, ["correct", str(CHECK_H5), str(LUT), "-o", str(tmp_path / "o")]))
    assert "is a session" in text and "not a look-up table" in text
    text = _one_line_error(CliRunner().invoke(cli, ["correct", str(LUT), str(LUT), "-o", str(tmp_path / "o.h5")]))
    assert "is a look-up table" in text
    text = _one_line_error(CliRunner().invoke(cli, ["evaluate", str(LUT), str(LUT)]))
    assert "is a look-up table" in text
    liberty = tmp_path / "liberty.csv"
    liberty.write_text("Time,w1,x1,y1,z1,loc1_x,loc1_y,loc1_z\n0,1,0,0,0,1,2,3\n")
    text = _one_line_error(CliRunner().invoke(cli, ["correct", str(LUT), str(liberty), "-o", str(tmp_path / "o.csv")]))
    assert "another program's format" in text and "ivc collect STEP --source replay:FILE" in text


# ---- item 6: a tracker model on points it was not calibrated for ----------------------------------------------------

@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """A tracker calibrated on a rig CSV; held-out points of the same rig, and of a source fixturing it never saw."""
    from ivc.collect.rig_csv import write_rig_csv
    from ivc.dipole.tracker import Tracker
    from ivc.pose.calibrate import Fixtures, rigid_transform
    from ivc.rotations import from_rotvec, to_matrix
    from ivc.sim.stage import stage_pattern, stage_recording

    rng = np.random.default_rng(41)
    folder = tmp_path_factory.mktemp("rig")
    truth = Tracker(np.eye(3) + 0.03 * rng.standard_normal((3, 3)), np.eye(3) + 0.03 * rng.standard_normal((3, 3)))
    seen = Fixtures(stage=rigid_transform(t=np.array([0.0, 0.26, 0.0])))
    turned = to_matrix(from_rotvec(np.array([0.0, 0.0, np.radians(60.0)])))
    unseen = Fixtures(source=rigid_transform(R=turned, t=np.array([0.03, 0.0, 0.02])),
                      stage=rigid_transform(t=np.array([0.0, 0.26, 0.0])))
    J_so, J_st = stage_pattern(rz_deg=(-90.0, 0.0, 90.0))
    for name, fixtures in (("calibration.csv", seen), ("held_out.csv", seen), ("other_fixturing.csv", unseen)):
        S = stage_recording(truth, fixtures, J_so, J_st, noise_relative=1e-4, rng=rng)
        write_rig_csv(folder / name, S, J_st)
    model = folder / "tracker.json"
    result = CliRunner().invoke(cli, ["tracker", "calibrate", str(folder / "calibration.csv"), "-o", str(model),
                                      "--one-centre", "--no-sign-check", "--json"])
    assert result.exit_code == 0, result.output
    return folder


def test_tracker_check_warns_with_the_numbers_on_another_fixturing(rig):
    """`ivc tracker check` on an unseen source fixturing: 171 % residue, 313 mm RMS, exit 0 and no note."""
    runner = CliRunner()
    same = runner.invoke(cli, ["tracker", "check", str(rig / "tracker.json"), str(rig / "held_out.csv")])
    assert same.exit_code == 0 and "WARNING" not in same.output, same.output
    other = runner.invoke(cli, ["tracker", "check", str(rig / "tracker.json"), str(rig / "other_fixturing.csv")])
    assert other.exit_code == 0, other.output
    own = json.loads((rig / "tracker.json").read_text())["calibration"]["report"]["calibration"]
    report = json.loads(runner.invoke(cli, ["tracker", "check", str(rig / "tracker.json"),
                                            str(rig / "other_fixturing.csv"), "--json"]).stdout)
    assert report["residue_rms_percent"] > 5 * max(own["residue_rms_percent"], 0.2)
    warning = report["warning"]
    assert f"residue rms {report['residue_rms_percent']:.3g} %" in warning
    assert f"(the calibration's: {own['residue_rms_percent']:.3g} %)" in warning
    assert "WARNING: " + warning in other.output and "fixturing" in warning


def test_tracker_calibrate_refuses_a_check_pose_recording_given_as_a_rig_csv(tmp_path):
    out = tmp_path / "t.json"
    text = _one_line_error(CliRunner().invoke(cli, ["tracker", "calibrate", str(CHECK_CSV), "-o", str(out)]))
    assert "is a recording CSV" in text and "not a rig CSV" in text and "no time or sensor column" in text
    assert not out.exists()
    text = _one_line_error(CliRunner().invoke(cli, ["tracker", "calibrate", str(CHECK_H5), "-o", str(out)]))
    assert "is a session" in text and not out.exists()


# ---- items 10 and 11: options refused before any work ---------------------------------------------------------------

@pytest.mark.parametrize("args", [["predict", str(HEAD), "-o", "{tmp}/o.csv", "--rate", "1e12"],
                                  ["predict", str(HEAD), "--evaluate", "--rate", "1e12"],
                                  ["correct", str(LUT), "--live", "igtl://127.0.0.1:9", "--rate-hz", "1e12"],
                                  ["collect", "check", "--source", f"replay:{CHECK_CSV}", "-o", "{tmp}/s.h5",
                                   "--rate", "0"]])
def test_rates_outside_a_tracker_stream_are_refused_before_the_work(args, tmp_path):
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    text = _one_line_error(CliRunner().invoke(cli, args), code=(2,))
    assert "0.1" in text and "10000 Hz" in text or "above 0" in text
    assert list(tmp_path.iterdir()) == []


def test_the_library_refuses_the_same_rates():
    import ivc

    assert check_rate(None) is None and check_rate(240) == 240.0
    for bad in (1e12, 0.0, -5, float("nan"), "fast"):
        with pytest.raises(OptionsError, match="rate_hz"):
            check_rate(bad)
    with pytest.raises(OptionsError, match=r"rate_hz=1e\+12 Hz is outside"):
        ivc.predict_file(HEAD, "never.csv", ivc.PredictOptions(rate_hz=1e12))
    assert not Path("never.csv").exists()


def test_a_negative_seed_is_a_usage_error():
    text = _one_line_error(CliRunner().invoke(cli, ["predict", "--benchmark", "--seed", "-1"]), code=(2,))
    assert "--seed" in text and "-1" in text


@pytest.mark.parametrize("args", [["--live", "igtl://127.0.0.1:99999"],
                                  ["--live", "igtl://127.0.0.1:9", "--publish", "127.0.0.1:99999"]])
def test_a_port_out_of_range_is_refused_before_the_table_is_read(args, monkeypatch):
    import ivc.cli.correct as correct_cli

    monkeypatch.setattr(correct_cli, "live_corrector", lambda *a, **k: pytest.fail("the work started"))
    text = _one_line_error(CliRunner().invoke(cli, ["correct", str(LUT), *args, "--duration", "1"]))
    assert "99999" in text and "65535" in text


def test_an_itk_export_on_a_full_disk_is_one_line_and_leaves_nothing(tmp_path, monkeypatch):
    sitk = pytest.importorskip("SimpleITK")

    def full_disk(transform, path):
        Path(path).write_bytes(b"\x89HDF partial")  # ITK gets as far as part of the file
        raise RuntimeError("Exception thrown in SimpleITK WriteTransform: itkHDF5TransformIO.cxx:462:\nITK ERROR: "
                           f"HDF5TransformIOTemplate: H5Dwrite failed ({errno.errorcode[errno.ENOSPC]}: "
                           "No space left on device)")

    monkeypatch.setattr(sitk, "WriteTransform", full_disk)
    out = tmp_path / "field.h5"
    out.write_bytes(b"the previous export")
    text = _one_line_error(CliRunner().invoke(cli, ["export", str(LUT), "--format", "itk", "-o", str(out),
                                                    "--force"]))
    assert "could not write" in text and "disk full" in text and "No space left on device" in text
    assert out.read_bytes() == b"the previous export" and [p.name for p in tmp_path.iterdir()] == ["field.h5"]


# ---- messages that sent the user the wrong way ----------------------------------------------------------------------

def test_fit_with_too_few_frames_names_max_frames_not_the_sweep(small_session, tmp_path):
    """`--max-frames 1` said the samples were mostly invalid and to redo the sweep."""
    path = tmp_path / "s.h5"
    session_io.write(small_session[1], path)
    text = _one_line_error(CliRunner().invoke(cli, ["fit", str(path), "-o", str(tmp_path / "t.h5"),
                                                    "--max-frames", "1"]))
    assert "every 3000-th of the sweep's 3000 frames" in text and "a larger --max-frames N" in text
    assert "redo" not in text and "invalid" not in text


def test_live_with_no_server_reached_fails_and_says_so(tmp_path):
    """It exited 0 with 'median processing nan ms per batch'."""
    import socket

    with socket.socket() as probe:  # a port nothing listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    result = CliRunner().invoke(cli, ["correct", str(LUT), "--live", f"igtl://127.0.0.1:{port}", "--publish",
                                      "127.0.0.1:0", "--duration", "1"])
    text = _one_line_error(result, code=(1,))
    assert "never reached a tracking server" in text and "nan" not in text and "no batch processed" in text


def test_an_unwritable_output_folder_is_refused_before_the_work_and_named(tmp_path, monkeypatch):
    """A read-only folder was found only after the work, and the message named a hidden temporary file."""
    import tempfile

    import ivc.app.correct as correct_app
    from ivc.files import atomic_path

    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    text = _one_line_error(CliRunner().invoke(cli, ["correct", str(LUT), str(CHECK_CSV), "-o",
                                                    str(blocker / "out.csv")]))
    assert f"{blocker / 'out.csv'}: cannot write it" in text and "not a folder" in text

    def read_only(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(correct_app, "_Job", lambda *a, **k: pytest.fail("the work started"))
    monkeypatch.setattr(tempfile, "TemporaryFile", read_only)
    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    out = tmp_path / "locked" / "out.csv"
    for args in (["correct", str(LUT), str(CHECK_CSV), "-o", str(out)],
                 ["collect", "check", "--source", "sim", "--frames", "100", "-o", str(tmp_path / "locked" / "s.h5")],
                 ["predict", str(HEAD), "--evaluate", "--plot", str(tmp_path / "p.png")],
                 ["export", str(LUT), "--format", "csv", "-o", str(out)]):
        text = _one_line_error(CliRunner().invoke(cli, args))
        assert "is not writable (Permission denied)" in text and ".tmp" not in text, args
    with pytest.raises(PermissionError) as raised, atomic_path(out):
        pass
    assert raised.value.filename == str(out) and ".tmp" not in str(raised.value)


@pytest.mark.parametrize("separator", [";", "\t"])
def test_a_csv_with_another_separator_is_named_as_the_problem(tmp_path, separator):
    """A semicolon or decimal-comma CSV got 'the header needs one time column ...'."""
    path = tmp_path / "semicolons.csv"
    path.write_text("\n".join(separator.join(c.replace(".", ",") for c in line.split(","))
                              for line in CHECK_CSV.read_text().splitlines()[:5]) + "\n")
    text = _one_line_error(CliRunner().invoke(cli, ["correct", str(LUT), str(path), "-o", str(tmp_path / "o.csv")]))
    assert "its columns are separated by" in text and "commas" in text and "0.25, not 0,25" in text


def test_evaluate_draws_no_progress_bar_into_a_redirected_log(tmp_path):
    result = CliRunner().invoke(cli, ["predict", str(_short_head(tmp_path)), "--evaluate", "--filter", "poly1",
                                      "--horizon", "25ms"])
    assert result.exit_code == 0, result.output
    assert "filter/s" not in result.output and "\r" not in result.output


def test_tracker_calibrate_warns_of_stage_positions_in_another_unit(rig, tmp_path):
    """ILEMT positions in m instead of mm ended in 'source_moments is singular' or a model of points 6 mm away."""
    lines = (rig / "calibration.csv").read_text().splitlines()
    metres_read_as_mm = tmp_path / "mm.csv"
    metres_read_as_mm.write_text("\n".join([lines[0].replace("x,y,z", "x_mm,y_mm,z_mm"), *lines[1:]]) + "\n")
    result = CliRunner().invoke(cli, ["tracker", "calibrate", str(metres_read_as_mm), "-o", str(tmp_path / "t.json"),
                                      "--one-centre", "--no-sign-check"])
    assert "mm.csv: its stage positions span 0.1 mm in all" in result.stderr and "in metres" in result.stderr
    same = CliRunner().invoke(cli, ["tracker", "check", str(rig / "tracker.json"), str(rig / "held_out.csv")])
    assert "stage positions span" not in same.output


def test_fixtures_print_checks_its_folders_before_building_the_part(tmp_path, monkeypatch):
    import ivc.fixtures.printing as printing

    monkeypatch.setattr(printing, "build_part", lambda *a, **k: pytest.fail("the part was built"))
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    text = _one_line_error(CliRunner().invoke(cli, ["fixtures", "print", "cube", "-o", str(tmp_path / "cube.stl"),
                                                    "--preview", str(blocker / "cube.png")]))
    assert f"{blocker / 'cube.png'}: cannot write it" in text and "not a folder" in text
