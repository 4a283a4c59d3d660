"""What new users feed the commands: outputs that are inputs, absurd options, dropouts, files from Excel and
other tools. Each gets a one-line refusal or a correct result, and no input is ever changed."""

import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from ivc import dipole, rotations
from ivc import session as session_io
from ivc.cli import cli
from ivc.collect import CsvError, rate_warning, read_csv, read_csv_columns, write_csv
from ivc.correct import INVALID_INPUT, Corrector
from ivc.errors import InputError, LutError, SessionError
from ivc.lut import read as read_lut
from ivc.lut import write as write_lut
from ivc.lut.build import FitOptions, check_grid_memory, fit_lut
from ivc.session import Step
from tests.helpers import distorted

ROOT = Path(__file__).resolve().parents[1]


def digest(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def one_line_refusal(result, *words):
    assert result.exit_code != 0, result.output
    assert "Traceback" not in result.output and result.exception is None or isinstance(result.exception, SystemExit)
    for word in words:
        assert word in result.output, result.output


@pytest.fixture
def lut_file(exact_table, tmp_path):  # noqa: F811
    path = tmp_path / "lut.h5"
    write_lut(exact_table, path)
    return path


def signal_step(rng, frames=20, sensors=2) -> Step:
    r, T, S = distorted(rng, frames * sensors)
    return Step(np.arange(frames) / 240.0, S.reshape(frames, sensors, 3, 3), sensor_ids=[f"S{k}" for k in
                                                                                           range(sensors)])


# ---- outputs that are inputs ------------------------------------------------------------------------------------

def _aliases(target: Path, tmp_path: Path) -> list[Path]:
    """The same file by its path, a symbolic link and a hard link."""
    symlink, hardlink = tmp_path / f"sym-{target.name}", tmp_path / f"hard-{target.name}"
    symlink.symlink_to(target)
    os.link(target, hardlink)
    return [target, symlink, hardlink]


def test_no_command_writes_over_one_of_its_inputs_even_with_force(lut_file, tmp_path, rng):
    csv_in = tmp_path / "rec.csv"
    write_csv(signal_step(rng), csv_in)
    session_file = tmp_path / "s.h5"
    session_io.write(session_io.Session(steps={"check": signal_step(rng)}), session_file)
    other = tmp_path / "other.csv"
    write_csv(signal_step(rng), other)
    commands = {  # command line with {} for the output, and the input the output aliases
        "fit": (["fit", session_file, "-o", "{}", "--force"], session_file),
        "correct input": (["correct", lut_file, csv_in, "-o", "{}", "--force"], csv_in),
        "correct table": (["correct", lut_file, csv_in, "-o", "{}", "--force"], lut_file),
        "correct tune-from": (["correct", lut_file, csv_in, "-o", "{}", "--force", "--predict", "mmdq2",
                               "--tune-from", other], other),
        "predict": (["predict", csv_in, "-o", "{}", "--force", "--horizon", "20ms"], csv_in),
        "predict tune-from": (["predict", csv_in, "-o", "{}", "--force", "--tune-from", other, "--horizon", "20ms"],
                              other),
        "export": (["export", lut_file, "--format", "hdf5", "-o", "{}", "--force"], lut_file),
        "collect": (["collect", "check", "--source", "replay:" + str(session_file), "-o", "{}", "--force"],
                    session_file),
    }
    before = {p: digest(p) for p in (csv_in, session_file, other, lut_file)}
    for what, (args, target) in commands.items():
        folder = tmp_path / what.replace(" ", "_")
        folder.mkdir()
        for alias in _aliases(target, folder):
            line = [str(alias) if a == "{}" else a for a in args]
            result = run(*line)
            one_line_refusal(result, "never overwritten")
    # a report directory that holds an input under one of the report's own names
    (tmp_path / "rep").mkdir()
    shadow = tmp_path / "rep" / "report.json"
    shadow.write_bytes(session_file.read_bytes())
    one_line_refusal(run("report", shadow, lut_file, "-o", tmp_path / "rep", "--force"), "never overwritten")
    assert {p: digest(p) for p in before} == before


def test_no_command_replaces_an_existing_output_without_force(lut_file, tmp_path, rng):
    csv_in = tmp_path / "rec.csv"
    write_csv(signal_step(rng), csv_in)
    taken = tmp_path / "taken"
    taken.write_bytes(b"precious")
    session_file = tmp_path / "s.h5"
    session_io.write(session_io.Session(steps={"check": signal_step(rng)}), session_file)
    for args in (["fit", session_file, "-o", taken], ["correct", lut_file, csv_in, "-o", taken],
                 ["predict", csv_in, "-o", taken], ["export", lut_file, "--format", "csv", "-o", taken],
                 ["collect", "protocol", "-o", taken, "--sweep-frames", "10"],
                 ["collect", "check", "--source", "replay:" + str(session_file), "-o", session_file.with_name("t.h5")]):
        if args[0] == "collect" and args[1] == "check":
            session_io.write(session_io.Session(steps={"check": signal_step(rng)}), args[-1])
            before = digest(args[-1])
            one_line_refusal(run(*args), "already recorded", "--force")
            assert digest(args[-1]) == before
            continue
        one_line_refusal(run(*args), "exists", "--force")
    assert taken.read_bytes() == b"precious"


def _deliverable_sigint() -> None:
    """In the child before it starts: SIGINT unblocked and at its default, as in a user's shell. An ignored or
    blocked SIGINT is inherited across exec (a test worker or a background job may have one), and Python raises
    no KeyboardInterrupt for a signal that never arrives: the 'interrupted' command would run to its end."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _interrupt(args, tmp_path, after_s, after_first_line=False):
    """Run ``ivc ARGS`` and send it SIGINT ``after_s`` seconds after it starts, or after its first line on stderr (so
    past its imports, whatever the machine's load); its exit code and stderr. A command that ends sooner is not
    waited for."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    process = subprocess.Popen([sys.executable, "-m", "ivc.cli", *map(str, args)], cwd=tmp_path, env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               preexec_fn=_deliverable_sigint)
    first = process.stderr.readline() if after_first_line else ""
    try:
        process.wait(timeout=after_s)
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=60)
    return process.returncode, first + err


@pytest.mark.slow
def test_an_interrupted_fit_or_collect_leaves_no_partial_output_and_the_input_intact(small_session, tmp_path):
    _, session = small_session
    session_file = tmp_path / "in.h5"
    session_io.write(session, session_file)
    before = digest(session_file)
    interrupted, tries = False, []
    for delay in (4.0, 2.5, 1.5, 0.8, 0.3):  # a fast machine may finish the small fit before the first delays
        code, err = _interrupt(["fit", session_file, "-o", tmp_path / "lut.h5"], tmp_path, delay)
        tries.append((delay, code, (tmp_path / "lut.h5").exists(), err[-300:]))
        if code != 0 and not (tmp_path / "lut.h5").exists():
            interrupted = True
            break
        # The fit finished first, or the signal came after the atomic rename (while the summary printed or the
        # interpreter exited): either way the table on disk must be whole.
        read_lut(tmp_path / "lut.h5")
        (tmp_path / "lut.h5").unlink()
    assert interrupted, f"no delay interrupted the fit: (delay s, exit code, table written, stderr) {tries}"
    # the collections say on stderr when they start simulating (imports done): interrupted 1 s into the work
    code, err = _interrupt(["collect", "protocol", "-o", tmp_path / "new.h5", "--sweep-frames", "200000"], tmp_path,
                           1.0, after_first_line=True)
    assert code != 0 and not (tmp_path / "new.h5").exists(), err
    code, err = _interrupt(["collect", "wand_sweep", "--source", "sim", "-o", session_file, "--force",
                            "--frames", "400000"], tmp_path, 1.0, after_first_line=True)
    assert code != 0, err
    assert digest(session_file) == before
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert leftovers == []


# ---- crashes ----------------------------------------------------------------------------------------------------

def test_an_all_zero_signal_matrix_is_flagged_invalid_and_the_rest_corrected(exact_table, rng, lut_file,  # noqa: F811
                                                                              tmp_path):
    r, T, S = distorted(rng, 10)
    S[3] = 0.0
    out = Corrector(exact_table).batch(S)
    assert out.flags[3] == INVALID_INPUT and np.all(np.isnan(out.position[3]))
    assert np.all(out.flags[np.arange(10) != 3] == 0)
    assert Corrector(exact_table).update(S[:5]).flags.tolist() == [0, 0, 0, INVALID_INPUT, 0]
    step = signal_step(rng, 10, 1)
    step.signal[4] = 0.0
    write_csv(step, tmp_path / "drop.csv")
    result = run("correct", lut_file, tmp_path / "drop.csv", "-o", tmp_path / "out.csv")
    assert result.exit_code == 0, result.output
    assert "1 invalid input" in result.output


def test_grids_too_large_for_memory_are_refused_before_any_work(small_session):
    with pytest.raises(InputError, match="GiB"):
        FitOptions(origin=(0, 0, 0), shape=(100_000, 100_000, 100_000))
    with pytest.raises(InputError, match="GiB"):
        check_grid_memory((1000, 1000, 1000))
    _, session = small_session
    start = time.perf_counter()
    with pytest.raises(InputError, match="coarser spacing"):
        fit_lut(session, FitOptions(spacing=0.001))
    assert time.perf_counter() - start < 5  # refused before the sweep is solved
    with pytest.raises(InputError, match="at most 1000 mm"):
        FitOptions(spacing=1e6)


@pytest.mark.parametrize("args, words", [
    (["--degree", "0"], ["--degree", "0"]),
    (["--max-frames", "0"], ["--max-frames"]),
    (["--min-support", "-1"], ["--min-support"]),
    (["--max-residual", "-1"], ["--max-residual"]),
    (["--max-residual", "nan"], ["--max-residual"]),
    (["--max-error-mm", "inf"], ["--max-error-mm"]),
    (["--grid", "1e9"], ["1000 mm"]),
    (["--grid", "0.001"], ["GiB"]),
    (["--grid", "0,0,0:100000,100000,100000:1"], ["GiB"]),
    (["--grid", "0,0,0:1,5,5:10"], ["--grid"]),
])
def test_fit_options_out_of_range_are_one_line_refusals(small_session, tmp_path, args, words):
    _, session = small_session
    path = tmp_path / "s.h5"
    session_io.write(session, path)
    one_line_refusal(run("fit", path, "-o", tmp_path / "lut.h5", *args), *words)
    assert not (tmp_path / "lut.h5").exists()


def test_frame_counts_and_rates_out_of_range_are_refused(tmp_path):
    one_line_refusal(run("collect", "check", "-o", tmp_path / "s.h5", "--frames", "10000000000"), "--frames")
    one_line_refusal(run("collect", "check", "-o", tmp_path / "s.h5", "--frames", "0"), "--frames")
    one_line_refusal(run("demo", "--sweep-frames", "-5"), "--sweep-frames")
    one_line_refusal(run("predict", "x.csv", "-o", tmp_path / "o.csv", "--rate", "0"), "--rate")
    assert not (tmp_path / "s.h5").exists()


def test_a_scalar_signal_dataset_and_a_table_of_byte_strings_are_refused(tmp_path, rng, exact_table):  # noqa: F811
    path = tmp_path / "s.h5"
    session_io.write(session_io.Session(steps={"check": signal_step(rng)}), path)
    with h5py.File(path, "a") as h5:
        del h5["steps/check/signal"]
        h5["steps/check/signal"] = 3.0
    with pytest.raises(SessionError, match="signal"):
        session_io.read(path)
    one_line_refusal(run("info", path), "signal")
    table = tmp_path / "t.h5"
    write_lut(exact_table, table)
    with h5py.File(table, "a") as h5:
        del h5["values"]
        h5["values"] = np.full(exact_table.values.shape, b"1.0")
    with pytest.raises(LutError, match="values"):
        read_lut(table)


# ---- files real users have ----------------------------------------------------------------------------------------

def _pose_csv(path, rows, header="time,sensor,x,y,z,qw,qx,qy,qz", encoding="utf-8", bom=False):
    text = header + "\n" + "\n".join(rows) + "\n"
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode(encoding))
    return path


def _rows(n=5, dt=1 / 240):
    return [f"{k * dt!r},S0,0.3,0.1,0.0,1,0,0,0" for k in range(n)]


def test_a_csv_saved_by_excel_with_a_bom_is_read(tmp_path):
    step = read_csv(_pose_csv(tmp_path / "excel.csv", _rows(), bom=True))
    assert step.n_frames == 5 and step.sample_rate_hz == 240


def test_a_csv_that_is_not_utf8_is_named_as_such(tmp_path):
    path = _pose_csv(tmp_path / "latin.csv", [r + ",Sonde é" for r in _rows()],
                     header="time,sensor,x,y,z,qw,qx,qy,qz,note", encoding="latin-1")
    with pytest.raises(CsvError, match="not UTF-8"):
        read_csv(path)


def test_a_partial_signal_column_set_is_refused(tmp_path):
    header = "time,sensor,x,y,z,qw,qx,qy,qz," + ",".join(f"s{i}{j}" for i in range(3) for j in range(3) if
                                                          (i, j) != (2, 2))
    path = _pose_csv(tmp_path / "partial.csv", [r + ",1,0,0,0,1,0,0,0" for r in _rows()], header=header)
    with pytest.raises(CsvError, match="missing s22"):
        read_csv(path)


@pytest.mark.parametrize("order", [[0, 2, 1, 3, 4], [0, 1, 1, 2, 3]])
def test_unsorted_or_repeated_times_are_refused(tmp_path, order):
    rows = _rows()
    path = _pose_csv(tmp_path / "shuffled.csv", [rows[k] for k in order])
    with pytest.raises(CsvError, match="time order") as refused:
        read_csv(path)
    assert "np.float64" not in str(refused.value) and "line 4: time " in str(refused.value)
    with pytest.raises(CsvError, match="time order"):
        read_csv(path, 240.0)  # --rate does not excuse them


def test_times_in_milliseconds_under_time_are_warned_about(tmp_path):
    step = read_csv(_pose_csv(tmp_path / "ms.csv", _rows(dt=1000 / 240)))
    assert "time_ms" in rate_warning(step)
    assert rate_warning(read_csv(_pose_csv(tmp_path / "s.csv", _rows()))) is None


def test_zero_quaternions_and_absurd_positions_are_refused(tmp_path):
    rows = _rows()
    rows[2] = rows[2].replace(",1,0,0,0", ",0,0,0,0")
    with pytest.raises(CsvError, match="line 4: the quaternion"):
        read_csv(_pose_csv(tmp_path / "zero.csv", rows))
    rows = _rows()
    rows[1] = rows[1].replace("0.3,0.1,0.0", "1e30,0.1,0.0")
    with pytest.raises(CsvError, match="line 3: the position is 1e\\+30 m"):
        read_csv(_pose_csv(tmp_path / "far.csv", rows))


def test_corrected_csv_keeps_extra_columns_the_input_unit_and_a_valid_that_agrees_with_the_flags(
        lut_file, tmp_path, rng, exact_table):  # noqa: F811
    step = signal_step(rng, 12, 2)
    step.signal[0, 1] = 0.0  # flagged (invalid input)
    p, R = dipole.closed_form_pose(step.signal.reshape(-1, 3, 3))
    q = rotations.from_matrix(R)
    q[1] = [1, 0, 0, 0]
    p[1] = [0.3, 0, 0]
    lines = []
    for f in range(12):
        for n in range(2):
            k = 2 * f + n
            numbers = [step.time[f], *(p[k] / 0.0254), *q[k], *step.signal[f, n].ravel()]
            text = [repr(float(v)) for v in numbers]
            lines.append(",".join([text[0], f"S{n}", *text[1:], f"trial-{f}", str(k % 3)]))
    header = ("time,sensor,x_in,y_in,z_in,qw,qx,qy,qz," + ",".join(f"s{i}{j}" for i in range(3) for j in range(3))
              + ",trial,flags")
    path = _pose_csv(tmp_path / "inch.csv", lines, header=header)
    result = run("correct", lut_file, path, "-o", tmp_path / "out.csv")
    assert result.exit_code == 0, result.output
    assert "written as 'input_flags'" in result.output
    out_header = (tmp_path / "out.csv").read_text().splitlines()[0].split(",")
    assert out_header[2:5] == ["x_in", "y_in", "z_in"] and "trial" in out_header and "input_flags" in out_header
    corrected, columns = read_csv_columns(tmp_path / "out.csv")
    assert columns.length_unit == "in"
    assert list(columns.extra["trial"][:, 0]) == [f"trial-{f}" for f in range(12)]
    flags = columns.extra["flags"].astype(int)
    assert flags[0, 1] == INVALID_INPUT
    np.testing.assert_array_equal(corrected.valid, flags == 0)
    out = Corrector(exact_table).batch(step.signal)
    ok = out.flags == 0
    np.testing.assert_allclose(corrected.position[ok], out.position[ok], atol=1e-12)


# ---- small things a new user trips on ---------------------------------------------------------------------------

def test_a_horizon_without_a_unit_is_refused(tmp_path, rng, lut_file):
    csv_in = tmp_path / "rec.csv"
    write_csv(signal_step(rng), csv_in)
    one_line_refusal(run("predict", csv_in, "-o", tmp_path / "p.csv", "--horizon", "0.05"), "no unit", "0.05ms",
                     "0.05s")
    one_line_refusal(run("correct", lut_file, csv_in, "-o", tmp_path / "c.csv", "--predict", "mmdq2",
                         "--horizon", "50"), "no unit")
    step = signal_step(rng, 40, 1)
    p, R = dipole.closed_form_pose(step.signal)
    poses = tmp_path / "poses.csv"
    write_csv(Step(step.time, None, p, rotations.from_matrix(R), sensor_ids=["S0"]), poses)
    result = run("predict", poses, "-o", tmp_path / "p.csv", "--horizon", "0.05s")
    assert result.exit_code == 0, result.output


@pytest.mark.slow
def test_demo_without_keep_names_no_file_it_deletes_and_draws_no_bars_off_a_terminal():
    result = run("demo", "--sweep-frames", "3000", "--check-frames", "300")
    assert result.exit_code == 0, result.output
    assert "ivc-demo-" not in result.output and "demo.h5" not in result.output
    assert "\r" not in result.output and "it/s" not in result.output  # no tqdm fragments in a log
    assert "ivc demo finished" in result.output


def test_the_cli_and_the_library_agree_that_refinement_is_on_by_default():
    help_text = run("fit", "--help").output
    assert "[default: refine]" in help_text and "--no-refine" in help_text and FitOptions().refine is True


def test_a_session_step_with_a_repeated_time_is_refused(tmp_path, rng):
    step = signal_step(rng, 5, 1)
    step.time = np.array([0.0, 0.1, 0.1, 0.2, 0.3])
    with pytest.raises(SessionError, match="frame 2 repeats the time"):
        session_io.write(session_io.Session(steps={"check": step}), tmp_path / "s.h5")


@pytest.mark.slow
def test_evaluate_and_report_survive_an_all_zero_signal(tmp_path):
    samples = ROOT / "sample_data" / "recordings"
    data = session_io.read(samples / "default_room_check.h5")
    data.steps["check"].signal[5, 0] = 0.0  # a dropout in a sample marked valid
    check = tmp_path / "zero.h5"
    session_io.write(data, check)
    lut_path = samples / "default_room_lut.h5"
    result = run("evaluate", lut_path, check, "--json")
    assert result.exit_code == 0, result.output
    result = run("report", check, lut_path, "-o", tmp_path / "report")
    assert result.exit_code == 0, result.output
    assert (tmp_path / "report" / "report.html").exists()
