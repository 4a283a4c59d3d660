"""`ivc predict` on recordings and `ivc predict --benchmark`."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from ivc import session as session_io
from ivc.cli import cli
from ivc.collect.replay import read_csv, write_csv
from ivc.predict import make
from ivc.predict.motion import head_motion
from ivc.session import Session, Step


def motion_step(frames=800, sensors=2):
    q = np.stack([head_motion("moderate", frames, seed=s).measured for s in range(sensors)], axis=1)
    rate = 120.0
    return Step(np.arange(frames) / rate, None, np.zeros((frames, sensors, 3)), q, np.ones((frames, sensors), bool),
                rate, None, "synthetic head motion", {})


def test_predict_csv_and_session_match_the_library(tmp_path):
    step = motion_step()
    csv_in, csv_out = tmp_path / "head.csv", tmp_path / "ahead.csv"
    write_csv(step, csv_in)
    runner = CliRunner()
    result = runner.invoke(cli, ["predict", str(csv_in), "--filter", "dqekf-cv", "--horizon", "50ms",
                                 "-o", str(csv_out)])
    assert result.exit_code == 0, result.output
    got = read_csv(csv_out).quaternion
    expected = make("dqekf-cv", 120.0).predict(step.quaternion, 0.05)[0]
    assert np.allclose(got[5:], expected[5:], atol=1e-12)
    assert np.allclose(got[0], step.quaternion[0])  # no prediction yet: the measurement is kept

    session_file, out_file = tmp_path / "s.h5", tmp_path / "p.h5"
    session_io.write(Session("+x", {"check": step}), session_file)
    result = runner.invoke(cli, ["predict", str(session_file), "--filter", "mmdq2", "--horizon", "0.075s",
                                 "-o", str(out_file)])
    assert result.exit_code == 0, result.output
    out = session_io.read(out_file)
    assert np.allclose(out.steps["check"].quaternion[5:], make("mmdq2").predict(step.quaternion, 0.075)[0][5:])
    assert out.steps["check"].attrs["prediction_horizon_s"] == 0.075

    refused = runner.invoke(cli, ["predict", str(csv_in), "-o", str(csv_in), "--force"])
    assert refused.exit_code != 0 and "never overwritten" in refused.output
    again = runner.invoke(cli, ["predict", str(csv_in), "-o", str(csv_out)])
    assert again.exit_code != 0 and "exists" in again.output
    bad = runner.invoke(cli, ["predict", str(csv_in), "-o", str(tmp_path / "x.csv"), "--horizon", "fast"])
    assert bad.exit_code != 0 and "50ms" in bad.output


def test_predict_tune_estimates_the_noise_from_the_input(tmp_path):
    from ivc.predict.tuning import estimate

    step = motion_step(frames=1500)
    csv_in, csv_out = tmp_path / "head.csv", tmp_path / "ahead.csv"
    write_csv(step, csv_in)
    result = CliRunner().invoke(cli, ["predict", str(csv_in), "--filter", "q-ekf", "--tune", "-o", str(csv_out)])
    assert result.exit_code == 0, result.output
    assert "Q-EKF sigma_v" in result.output and "λ quartiles" in result.output
    tuning = estimate(step.quaternion, 120.0)
    expected = make("q-ekf", 120.0, tuning).predict(step.quaternion, 0.05)[0]
    assert np.allclose(read_csv(csv_out).quaternion[5:], expected[5:], atol=1e-12)
    short = tmp_path / "short.csv"
    write_csv(motion_step(frames=30), short)
    refused = CliRunner().invoke(cli, ["predict", str(short), "--filter", "mmdq2", "--tune", "-o",
                                       str(tmp_path / "s.csv")])
    assert refused.exit_code != 0 and "gap-free stretch" in refused.output


def test_predict_benchmark_prints_the_tables(tmp_path):
    plot = tmp_path / "h.png"
    args = ["predict", "--benchmark", "--frames", "1500", "--motion", "moderate", "--filter", "none",
            "--filter", "dqekf-cv", "--plot", str(plot)]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert "% overshoot" in result.output and "50 med" in result.output and "angular-velocity" in result.output
    assert "output SNR (dB)" in result.output
    assert plot.stat().st_size > 5000
    data = json.loads(CliRunner().invoke(cli, args[:-2] + ["--json"]).stdout)
    rows = {d["filter"]: d["rows"] for d in data}
    assert rows["dqekf-cv"][6]["mean"] < rows["none"][6]["mean"]
    tuned = CliRunner().invoke(cli, args[:-2] + ["--tune"])
    assert tuned.exit_code == 0 and "DQ    sigma_v" in tuned.output and "tuned on the set above" in tuned.output


@pytest.mark.slow
def test_compensators_prints_table1_and_the_designs_it_scored():
    from ivc.predict.studies import compensator

    result = CliRunner().invoke(cli, ["predict", "--compensators", "--evaluations", "15", "--json"])
    assert result.exit_code == 0, result.output
    designs = json.loads(result.stdout)
    assert set(designs) == {"default", "twist", "hybrid"}
    records = compensator.yaw_records(seed=0)
    for name, d in designs.items():  # the printed ratios are those of the printed W_r
        assert list(d["ratios"].values()) == list(compensator.score(np.array(d["W"]), records).ratios)
        assert tuple(d["paper"]) == compensator.PAPER_TABLE1[name]
    twist = designs["twist"]["ratios"]["twist"]
    assert twist <= designs["default"]["ratios"]["twist"]  # Powell starts at the default and only descends


def test_correct_predict_tune_tunes_to_the_trusted_samples():
    """`ivc correct --predict NAME --tune`: the filter tuned on the corrected step's trusted samples only."""
    from ivc.correct.solver import OUTSIDE
    from ivc.predict.steps import predicted_step
    from ivc.predict.tuning import estimate

    step = motion_step(frames=1500)
    flags = np.zeros(step.valid_mask.shape, np.uint8)
    flags[700:760, 0] = OUTSIDE  # untrusted: must neither tune nor drive the filter
    got, _ = predicted_step(step, "mmdq2", 0.05, tune=True, valid=flags == 0)
    tuning = estimate(step.quaternion, 120.0, valid=flags == 0)
    expected = make("mmdq2", 120.0, tuning).predict(step.quaternion, 0.05, flags == 0)[0]
    usable = np.all(np.isfinite(expected), axis=-1)
    assert np.allclose(got.quaternion[usable], expected[usable], atol=1e-12)
    assert got.attrs["tuned_from_input"] and got.attrs["predicted_with"] == "mmdq2"
    plain, _ = predicted_step(step, "mmdq2", 0.05, tune=False, valid=flags == 0)
    assert not plain.attrs["tuned_from_input"] and not np.allclose(plain.quaternion[usable], got.quaternion[usable])


def test_predict_tune_from_another_recording(tmp_path):
    """--tune-from: the thesis's separate tuning set; a session's orientation steps are pooled."""
    from ivc.predict.tuning import estimate

    step, other = motion_step(frames=900), motion_step(frames=1500, sensors=1)
    other.quaternion = np.stack([head_motion("aggressive", 1500, seed=9).measured], axis=1)
    csv_in, csv_tune, out = tmp_path / "head.csv", tmp_path / "tune.csv", tmp_path / "ahead.csv"
    write_csv(step, csv_in)
    write_csv(other, csv_tune)
    runner = CliRunner()
    result = runner.invoke(cli, ["predict", str(csv_in), "--filter", "mmdq2", "--tune-from", str(csv_tune),
                                 "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert f"--tune-from {csv_tune}:\ntuning from " in result.output
    tuning = estimate([read_csv(csv_tune).quaternion], 120.0)
    expected = make("mmdq2", 120.0, tuning).predict(step.quaternion, 0.05)[0]
    assert np.allclose(read_csv(out).quaternion[5:], expected[5:], atol=1e-12)

    session_file = tmp_path / "tune.h5"
    session_io.write(Session("+x", {"check": read_csv(csv_tune), "wand_sweep": read_csv(csv_in)}), session_file)
    out_h5 = tmp_path / "ahead.h5"
    h5_in = tmp_path / "head.h5"
    session_io.write(Session("+x", {"check": read_csv(csv_in)}), h5_in)
    result = runner.invoke(cli, ["predict", str(h5_in), "--filter", "mmdq2", "--tune-from", str(session_file),
                                 "-o", str(out_h5)])
    assert result.exit_code == 0, result.output
    pooled = estimate([read_csv(csv_tune).quaternion, read_csv(csv_in).quaternion], 120.0)
    got = session_io.read(out_h5).steps["check"]
    assert np.allclose(got.quaternion[5:], make("mmdq2", 120.0, pooled).predict(step.quaternion, 0.05)[0][5:],
                       atol=1e-12)
    assert got.attrs["tuned_from"] == str(session_file) and not got.attrs["tuned_from_input"]

    slow = tmp_path / "slow.csv"
    write_csv(motion_step(frames=900), slow)
    text = slow.read_text().splitlines()
    rows = [line.split(",") for line in text[1:]]
    slow.write_text("\n".join([text[0]] + [",".join([f"{float(r[0]) * 2:.9f}"] + r[1:]) for r in rows]) + "\n")
    for args, message in ((["--tune-from", str(slow)], "recording at 60 Hz"),
                          (["--tune", "--tune-from", str(csv_tune)], "not both")):
        refused = runner.invoke(cli, ["predict", str(csv_in), "--filter", "mmdq2", *args, "-o",
                                      str(tmp_path / "x.csv")])
        assert refused.exit_code != 0 and message in refused.output, refused.output
    refused = runner.invoke(cli, ["predict", "--benchmark", "--tune-from", str(csv_tune)])
    assert refused.exit_code != 0 and "synthetic" in refused.output
    untuned = runner.invoke(cli, ["predict", str(csv_in), "--filter", "poly2", "--tune-from", str(csv_tune),
                                  "-o", str(tmp_path / "poly.csv")])
    assert untuned.exit_code == 0 and "poly2 has no noise model to tune" in untuned.output
    assert np.allclose(read_csv(tmp_path / "poly.csv").quaternion[20:],
                       make("poly2").predict(step.quaternion, 0.05)[0][20:], atol=1e-12)


def test_correct_tune_from_needs_a_filter_and_the_stream_rate(tmp_path):
    rec = tmp_path / "rec.csv"
    write_csv(motion_step(frames=900), rec)
    runner = CliRunner()
    refused = runner.invoke(cli, ["correct", str(rec), "--tune-from", str(rec), "--live", "igtl://127.0.0.1:1"])
    assert refused.exit_code != 0 and "give --predict NAME" in refused.output
    refused = runner.invoke(cli, ["correct", str(rec), "--predict", "mmdq2", "--tune-from", str(rec),
                                  "--live", "igtl://127.0.0.1:1", "--rate-hz", "240"])
    assert refused.exit_code != 0 and "recording at 120 Hz" in refused.output and "--rate-hz" in refused.output
