"""`ivc predict --evaluate`, the default filter, and other programs' recordings through `ivc predict` and `ivc info`."""

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ivc import rotations
from ivc.cli import cli
from ivc.collect import read_recording
from ivc.collect.replay import read_csv
from ivc.predict import make
from ivc.predict.motion import head_motion
from ivc.predict.recording import score

SAMPLES = Path(__file__).resolve().parents[1] / "sample_data" / "recordings"


def _trace(path: Path, frames=1500, seed=0) -> Path:
    """A head trace as a headset logs it: jittered 60 Hz time stamps, sign flips, a few stale repeats."""
    rng = np.random.default_rng(seed)
    q = head_motion("moderate", frames, rate_hz=60.0, seed=seed).measured
    t = np.cumsum(rng.uniform(0.012, 0.022, frames))
    q[::5] *= -1
    q[40::50] = q[39::50][: len(q[40::50])]
    rows = [f"{float(t[k])!r} {k // 600} " + " ".join(repr(float(v)) for v in q[k]) for k in range(frames)]
    path.write_text("timestamp viewpoint w x y z\n" + "\n".join(rows) + "\n")
    return path


def test_evaluate_prints_the_table_and_writes_the_plot(tmp_path):
    trace = _trace(tmp_path / "head.txt")
    png = tmp_path / "error.png"
    result = CliRunner().invoke(cli, ["predict", str(trace), "--evaluate", "--horizon", "25ms,50ms",
                                      "--filter", "dqekf-cv", "--plot", str(png)])
    assert result.exit_code == 0, result.output
    assert "head-orientation trace" in result.output and "jitter" in result.output
    assert "repeated samples dropped: 30" in result.output
    lines = {line.split()[0]: line.split()[1:] for line in result.output.splitlines()
             if line.split() and line.split()[0] in ("none", "poly1", "dqekf-cv")}
    assert set(lines) == {"none", "poly1", "dqekf-cv"}
    step, _ = read_recording(trace)
    expected = score([make("dqekf-cv", step.sample_rate_hz)], step.quaternion[:, 0], step.time, [0.025, 0.05])[0]
    assert float(lines["dqekf-cv"][3]) == pytest.approx(expected.at(0.05)["median"], abs=0.006)
    assert float(lines["dqekf-cv"][4]) == pytest.approx(expected.at(0.05)["p95"], abs=0.06)
    assert png.stat().st_size > 10_000
    refused = CliRunner().invoke(cli, ["predict", str(trace), "--evaluate", "-o", str(tmp_path / "x.csv")])
    assert refused.exit_code != 0 and "--evaluate writes no -o OUTPUT" in refused.output


def test_default_filter_predicts_a_trace_at_its_own_time_steps(tmp_path):
    trace = _trace(tmp_path / "head.txt", frames=900)
    out = tmp_path / "ahead.csv"
    result = CliRunner().invoke(cli, ["predict", str(trace), "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert "predicted 50 ms ahead with auto" in result.output and "sign continuous" in result.output
    step, _ = read_recording(trace)
    expected = make("auto", step.sample_rate_hz).predict(step.quaternion, 0.05, time=step.time)[0]
    expected = np.where(np.isfinite(expected), expected, step.quaternion)
    got = read_csv(out)
    assert np.allclose(got.time, step.time)
    assert rotations.angle_between(got.quaternion, expected).max() < 1e-12


def test_info_reports_rate_jitter_and_import_quirks(tmp_path):
    trace = _trace(tmp_path / "head.txt", frames=300)
    result = CliRunner().invoke(cli, ["info", str(trace)])
    assert result.exit_code == 0, result.output
    assert "imported" in result.output and "Hz (median step" in result.output and "jitter" in result.output
    assert "repeated samples dropped: 6" in result.output
    # `ivc correct` refuses a tracker's own log, so info does not send the user there; it names the way in
    assert "ivc correct LUT FILE" not in result.output and "--source replay:FILE" in result.output


def test_correct_predict_alone_uses_the_default(tmp_path):
    lut, check = SAMPLES / "default_room_lut.h5", SAMPLES / "default_room_check.csv"
    plain, ahead = tmp_path / "plain.csv", tmp_path / "ahead.csv"
    runner = CliRunner()
    assert runner.invoke(cli, ["correct", str(lut), str(check), "-o", str(plain)]).exit_code == 0
    result = runner.invoke(cli, ["correct", str(lut), str(check), "-o", str(ahead), "--predict"])
    assert result.exit_code == 0, result.output
    assert "trusted samples" in result.output and "Hz (median step" in result.output
    a, b = read_csv(plain), read_csv(ahead)
    assert np.allclose(a.position, b.position)
    assert a.quaternion.shape == b.quaternion.shape
