"""Pose-only trackers: the inverse pose map, mapping from reported poses, the CLI and the live loop on them."""

import socket
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from click.testing import CliRunner
from pyigtl import TransformMessage

from ivc import lut, rotations
from ivc import session as session_io
from ivc.cli.main import cli
from ivc.collect.replay import write_csv
from ivc.correct import HIGH_RESIDUAL, INVALID_INPUT, NOT_CONVERGED, OUTSIDE, Corrector
from ivc.correct.evaluate import check_errors, evaluate, rigid_alignment, summarise
from ivc.correct.reported import PoseCorrector
from ivc.errors import InputError
from ivc.fixtures.report import fixture_report, pose_fixture_report
from ivc.live import LiveCorrector
from ivc.live.igtl import Framer
from ivc.lut import FitOptions, HarmonicFit
from ivc.pose.reported import invert_distortion
from ivc.pose.tracker_solver import distortion
from ivc.report.compute import POSE_ONLY, check_view, gather
from ivc.session import Session
from tests.helpers import CENTRE, ball, quadratic_field


def reported(rng, n, radius=0.15, solver="closed-form"):
    """True poses in the exact table's field and what a tracker with ``solver`` reports for them."""
    r = ball(rng, n, radius)
    T = rotations.to_matrix(rotations.random(n, rng))
    v, C = distortion(r, quadratic_field(r), solver=solver)
    return r, T, v, C @ T


def tracks(rng, frames, sensors=4, step=1e-3):
    """Four sensors moving smoothly (random walks of ``step`` m per frame) and what the tracker reports, as
    frames of ``sensors`` samples: (frames * sensors) rows, sensor k of frame f at row f * sensors + k."""
    start = ball(rng, sensors, 0.1)
    r = (start[None] + np.cumsum(step * rng.standard_normal((frames, sensors, 3)), axis=0)).reshape(-1, 3)
    T = rotations.to_matrix(rotations.random(len(r), rng))
    v, C = distortion(r, quadratic_field(r))
    return r, T, v, C @ T


def without_signals(session: Session) -> Session:
    return Session(session.hemisphere, {k: replace(s, signal=None) for k, s in session.steps.items()},
                   session.truth, session.attrs)


def test_noise_free_round_trip_recovers_the_true_pose(exact_table, rng):
    r, T, v, Q = reported(rng, 3000)
    assert np.median(np.linalg.norm(v - r, axis=1)) > 5e-3  # a real distortion
    out = PoseCorrector(exact_table).batch(v, rotations.from_matrix(Q))
    assert np.all(out.flags == 0)
    assert np.abs(out.position - r).max() < 1e-9
    assert rotations.angle_between(out.quaternion, rotations.from_matrix(T)).max() < 1e-9
    assert np.all(out.residual < 1e-10)


@pytest.mark.slow
def test_round_trip_with_the_least_squares_tracker_model(exact_table, rng):
    r, T, v, Q = reported(rng, 40, solver="least-squares")
    assert PoseCorrector(exact_table, solver="least-squares").solver == "least-squares"
    out = PoseCorrector(exact_table, solver="least-squares").batch(v, rotations.from_matrix(Q))
    assert np.all(out.flags == 0)
    assert np.abs(out.position - r).max() < 1e-9
    assert rotations.angle_between(out.quaternion, rotations.from_matrix(T)).max() < 1e-9
    # assuming the wrong solver costs accuracy: the closed form does not undo a least-squares tracker
    wrong = PoseCorrector(exact_table).batch(v, rotations.from_matrix(Q))
    assert np.median(np.linalg.norm(wrong.position - r, axis=1)) > 1e-6


def test_compiled_inversion_matches_the_numpy_reference(exact_table, rng):
    _, _, v, Q = reported(rng, 300)
    field = exact_table.field()
    reference = invert_distortion(v, lambda p: field.evaluate(p)[0])
    out = PoseCorrector(exact_table).batch(v, rotations.from_matrix(Q))
    np.testing.assert_allclose(out.position, reference.position, atol=1e-10)


def test_streaming_matches_batch(exact_table, rng):
    _, _, v, Q = reported(rng, 400)
    corrector = PoseCorrector(exact_table)
    batch = corrector.batch(v, rotations.from_matrix(Q))
    streamed = [corrector.update(v[k : k + 4], Q[k : k + 4], sensors="abcd") for k in range(0, 400, 4)]
    np.testing.assert_allclose(np.concatenate([s.position for s in streamed]), batch.position, atol=1e-10)
    q = np.concatenate([s.quaternion for s in streamed])
    assert rotations.angle_between(q, batch.quaternion).max() < 1e-9
    assert all(np.all(s.flags == 0) for s in streamed)


def test_compiled_stream_frame_is_the_batch_computation_from_the_same_start(exact_table, rng):
    """A frame whose sensors continue their tracks goes through one compiled call; given the same warm starts
    the batch's path gives the same numbers, bit for bit, and the same new warm starts."""
    _, _, v, Q = tracks(rng, 10)
    Q[9] = np.nan  # an invalid sample mid-stream: flagged, and its sensor's track restarts
    stream = PoseCorrector(exact_table)
    stream.update(v[:4], Q[:4], sensors="abcd")  # starts every track (through the batch's path)
    for k in range(4, 40, 4):
        offsets = stream.warm_starts("abcd")
        expected = stream.correct_from(v[k : k + 4], Q[k : k + 4], offsets)
        out = stream.update(v[k : k + 4], Q[k : k + 4], sensors="abcd")
        for name in ("position", "quaternion", "flags", "residual", "iterations"):
            np.testing.assert_array_equal(getattr(out, name), getattr(expected, name), err_msg=name)
        ok = out.flags == 0
        after = stream.warm_starts("abcd")
        assert np.array_equal(np.isfinite(after).all(axis=1), ok)
        np.testing.assert_array_equal(after[ok], (out.position - v[k : k + 4])[ok])
    assert stream.update(v[8:12], Q[8:12], sensors="abcd").flags[1] == INVALID_INPUT
    stream.update(v[12:16], Q[12:16], sensors="abcd")
    stream.reset(["c", "unknown"])  # the named sensors only (a name never seen: nothing to forget)
    starts = stream.warm_starts("abcd")
    assert np.isnan(starts[2]).all() and np.isfinite(starts[[0, 1, 3]]).all()
    stream.reset()
    stream.warm_up(v[0])  # runs the compiled steps, touches no sensor's warm start
    assert np.isnan(stream.warm_starts("abcd")).all()
    with pytest.raises(InputError, match="sensor names"):
        stream.update(v[:4], Q[:4], sensors="abc")


@pytest.mark.slow
def test_flags_mean_what_they_say(exact_table, rng):
    r, T, v, Q = reported(rng, 4)
    q = rotations.from_matrix(Q)
    v_bad = v.copy()
    v_bad[1] = CENTRE + [0.6, 0.0, 0.0]  # reported far outside the mapped volume
    v_bad[2] = -CENTRE  # in the other hemisphere: no true position in +x is reported there
    v_bad[3, 0] = np.nan
    out = PoseCorrector(exact_table).batch(v_bad, q)
    assert out.flags[0] == 0
    assert out.flags[1] & OUTSIDE
    assert out.flags[2] & (HIGH_RESIDUAL | NOT_CONVERGED)
    assert out.flags[3] == INVALID_INPUT and np.isnan(out.position[3]).all()
    assert PoseCorrector(exact_table).batch(v, q, valid=np.array([True, False, True, True])).flags[1] == INVALID_INPUT
    with pytest.raises(InputError, match="quaternions"):
        PoseCorrector(exact_table).batch(v, q[:2])


def test_rigid_alignment_recovers_a_rigid_map(rng):
    p = rng.standard_normal((50, 3))
    R = rotations.to_matrix(rotations.random(1, rng))[0]
    R_fit, t_fit = rigid_alignment(p, p @ R.T + [1.0, 2.0, 3.0])
    np.testing.assert_allclose(R_fit, R, atol=1e-12)
    np.testing.assert_allclose(t_fit, [1.0, 2.0, 3.0], atol=1e-12)


@pytest.fixture(scope="module")
def pose_only_table(small_session):
    _, session = small_session
    poses = without_signals(session)
    return poses, lut.fit_lut(poses, FitOptions(fitter=HarmonicFit(degree=5), max_frames=1500))


@pytest.mark.slow
def test_mapping_from_reported_poses_alone(small_session, pose_only_table):
    _, signals = small_session
    poses, table = pose_only_table
    assert table.fit["input"] == "reported poses" and table.fit["tracker_solver"] == "closed-form"
    assert table.fit["cube"]["vertex_position_rms_mm"] < 0.1
    typed = table.report  # the fit report, typed as every fit path's
    assert typed.input == "reported poses" and typed.reported_poses.tracker_solver == "closed-form"
    assert typed.reported_poses.vertex_position_rms_mm == table.fit["cube"]["vertex_position_rms_mm"]
    assert typed.degree == 5 and typed.refinement == () and typed.to_dict() == table.fit
    report = evaluate(table, poses)
    assert report["input"] == "reported poses"
    # the same session with its signals, through the signal path, for comparison
    signal_report = evaluate(lut.fit_lut(signals, FitOptions(refine=False)), signals)
    assert signal_report["input"] == "signals"
    assert report["corrected"] >= 0.9 * signal_report["corrected"] > 0
    assert report["ivc"]["position_mm"]["p50"] < 0.2
    assert report["ivc"]["position_mm"]["p50"] < 0.01 * report["dipole"]["position_mm"]["p50"]
    assert report["ivc"]["orientation_mrad"]["p50"] < 1.0
    assert report["ivc_aligned"]["position_mm"]["p50"] < 0.2


@pytest.mark.slow
def test_cli_end_to_end_on_a_pose_only_session_and_csv(pose_only_table, tmp_path):
    poses, table = pose_only_table
    session_file, lut_file = tmp_path / "poses.h5", tmp_path / "map.h5"
    session_io.write(poses, session_file)
    lut.write(table, lut_file)
    runner = CliRunner()
    result = runner.invoke(cli, ["correct", str(lut_file), str(session_file), "-o", str(tmp_path / "fixed.h5"),
                                 "--step", "check"])
    assert result.exit_code == 0, result.output
    assert "check: 300 samples" in result.output and "corrected" in result.output
    fixed = session_io.read(tmp_path / "fixed.h5")
    expected = PoseCorrector(table).batch(poses.steps["check"].position, poses.steps["check"].quaternion,
                                          poses.steps["check"].valid_mask)
    np.testing.assert_allclose(fixed.steps["check"].position[expected.ok], expected.position[expected.ok])
    write_csv(poses.steps["check"], tmp_path / "check.csv")
    result = runner.invoke(cli, ["correct", str(lut_file), str(tmp_path / "check.csv"), "-o",
                                 str(tmp_path / "fixed.csv")])
    assert result.exit_code == 0, result.output
    text = (tmp_path / "fixed.csv").read_text().splitlines()
    assert "flags" in text[0] and len(text) == 301
    result = runner.invoke(cli, ["evaluate", str(lut_file), str(session_file)])
    assert result.exit_code == 0, result.output
    assert "reported poses only" in result.output and "rigid fit" in result.output


@pytest.mark.slow
def test_fixtures_of_a_pose_only_session_go_through_the_pose_path(small_session, tmp_path):
    """`ivc fixtures` on reported poses alone: the cube's field through the tracker model, sensor 0 inverted;
    rebuilding signals from the poses instead (what it did before) gets sensor 0 wrong by millimetres."""
    _, session = small_session
    poses = without_signals(session)
    report = pose_fixture_report(poses)
    assert report["input"] == "reported poses" and report["sweep"]["residual_relative"] is None
    assert report["cube"]["vertex_position_rms_mm"] < 0.1
    assert report["sweep"]["converged_fraction"] > 0.99 and report["sweep"]["inversion_miss_um"]["max"] < 1.0
    pose_error = report["truth"]["sensor0_position_mm"]["p50"]
    rebuilt = fixture_report(poses)["truth"]["sensor0_position_mm"]["p50"]  # signals rebuilt from the poses
    assert pose_error < 0.3 and rebuilt > 5 * pose_error
    path = tmp_path / "poses.h5"
    session_io.write(poses, path)
    runner = CliRunner()
    result = runner.invoke(cli, ["fixtures", str(path)])
    assert result.exit_code == 0, result.output
    assert "from reported poses" in result.output and "reproduced to" in result.output
    refused = runner.invoke(cli, ["fixtures", str(path), "--method", "two-stage"])
    assert refused.exit_code == 2 and "reported poses only" in refused.output


@pytest.mark.slow
def test_report_corrects_pose_only_check_poses_through_the_pose_path(pose_only_table):
    """The report's accuracy section corrects reported poses as `ivc correct` does, with the tracker solver the
    table was fitted for (a signal Corrector handed over would lose it)."""
    poses, table = pose_only_table
    view, why = check_view(table, poses, None, "check", None, "the session")
    assert why is None
    expected = summarise(check_errors(PoseCorrector(table), poses))
    assert summarise(view.errors)["ivc"] == expected["ivc"] and expected["corrected"] > 0
    data = gather(poses, table)
    assert data.model is None and data.sweep is None and data.mapping_missing == (POSE_ONLY,)
    assert summarise(data.check.errors)["ivc"] == expected["ivc"]
    least_squares = replace(table, fit={**table.fit, "tracker_solver": "least-squares"})
    view, _ = check_view(least_squares, poses, None, "check", None, "the session")
    other = summarise(check_errors(PoseCorrector(least_squares), poses))
    assert summarise(view.errors)["ivc"] == other["ivc"] != expected["ivc"]


@pytest.mark.slow  # the live loop end to end over sockets
def test_live_transform_input_is_corrected_and_published_as_trusted_tdata(exact_table, rng):
    r, T, v, Q = tracks(rng, 8, sensors=3)  # three sensors moving as a stream's do
    m = np.zeros((8, 3, 4, 4))
    m[..., :3, :3], m[..., :3, 3], m[..., 3, 3] = Q.reshape(8, 3, 3, 3), 1000 * v.reshape(8, 3, 3), 1.0
    m = m.astype(np.float32)
    expected = PoseCorrector(exact_table).batch(m[..., :3, 3].astype(float) / 1000,
                                                rotations.from_matrix(m[..., :3, :3].astype(float)))
    assert np.all(expected.flags == 0)
    listener = socket.create_server(("127.0.0.1", 0))
    live = LiveCorrector(Corrector(exact_table), listener.getsockname(), ("127.0.0.1", 0))
    stop = threading.Event()
    runner = threading.Thread(target=live.run, kwargs={"stop": stop})
    runner.start()
    upstream, _ = listener.accept()
    consumer = socket.create_connection(live.publish_address)
    tdata, transforms = [], {}
    try:
        time.sleep(0.2)
        for k in range(8):
            upstream.sendall(b"".join(TransformMessage(m[k, n], timestamp=1000.0 + k / 240,
                                                       device_name=f"S{n}").pack() for n in range(3)))
        framer = Framer()
        consumer.settimeout(30.0)  # a bound on waiting for the next message, not a timing (interpreted kernels)
        deadline = time.monotonic() + 60
        while (len(transforms) < 24 or len(tdata) < 8) and time.monotonic() < deadline:
            framer.feed(consumer.recv(1 << 16))
            for f in framer.messages():
                if f.message_type == "TDATA":
                    tdata.append(f)
                elif f.message_type == "TRANSFORM":
                    transforms[f.device_name, round((f.timestamp - 1000.0) * 240)] = f
    finally:
        stop.set()
        runner.join(10)
        for s in (upstream, consumer, listener):
            s.close()
    assert len(transforms) == 24 and live.stats.corrected == 24 and live.stats.flagged == 0
    for (device, k), f in transforms.items():
        n = int(device[1])
        np.testing.assert_allclose(f.payload[:3, 3] / 1000, expected.position[k, n], atol=2e-6)
    # a TDATA "ivc" with the trusted sensors is published per round (each round: the three sensors once)
    assert len(tdata) >= 8 and all(f.device_name == "ivc" for f in tdata)


@pytest.mark.slow
def test_a_pose_only_fit_says_it_left_extension_sweeps_out(small_session):
    """The cube's map from reported poses (``fit_pose_lut``; ``fit_lut`` takes the whole-volume joint when a
    session has extension sweeps) covers the cube's reach: extension sweeps are named as not used, and `ivc fit`
    warns (docs/trust.md, "Poses beyond the map")."""
    from ivc.cli.fit import render_fit
    from ivc.lut.reported_build import fit_pose_lut

    _, session = small_session
    poses = without_signals(session)
    steps = dict(poses.steps)
    steps["extension_sweep_1"] = steps["wand_sweep"]
    extended = Session(poses.hemisphere, steps, poses.truth, poses.attrs)
    table = fit_pose_lut(extended, FitOptions(fitter=HarmonicFit(degree=3), max_frames=500))
    assert table.fit["extension_sweeps_ignored"] == ["extension_sweep_1"]
    assert table.report.extension_sweeps_ignored == ("extension_sweep_1",)
    assert "warning: extension_sweep_1 not used" in render_fit(table)
    # the self-calibration ran (refine, the default), lowered the wand's residual and says so
    calibration = table.fit["self_calibration"]
    assert calibration["rms_mm_by_iteration"][-1] < calibration["rms_mm_by_iteration"][0]
    assert "self-calibration: the wand's poses and the field fitted together" in render_fit(table)
    bare = fit_pose_lut(poses, FitOptions(fitter=HarmonicFit(degree=3), max_frames=500, refine=False))
    assert bare.fit["self_calibration"] is None and "self-calibration" not in render_fit(bare)
    plain = lut.fit_lut(poses, FitOptions(fitter=HarmonicFit(degree=3), max_frames=500))
    assert "extension_sweeps_ignored" not in plain.fit and plain.report.extension_sweeps_ignored == ()
    assert "not used" not in render_fit(plain)
