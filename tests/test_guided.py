"""Guided collection (issue 36, item 4): the stop rules fire on simulated data, a rehearsal is reproduced frame for
frame, a stop request keeps or drops as stated and never leaves a partial file."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest

from ivc.collect.guide import SourceFeed, collect_protocol, collect_step
from ivc.collect.rules import (
    OCTANT_NAMES,
    STATIC_ANGLE_SE,
    STATIC_POSITION_SE,
    CountRule,
    Frames,
    StaticRule,
    SweepRule,
)
from ivc.collect.stream import SessionSource, SourceEvent
from ivc.errors import InputError
from ivc.session import STEPS, Session, Step
from ivc.session import read as read_session
from tests.live_helpers import ArraySource, Unlabelled, static_cube


def test_a_static_step_stops_when_its_standard_errors_are_small(rng):
    position, quaternion = static_cube(5000, rng)
    step, report = collect_step(ArraySource(position, quaternion), "cube_calibration")
    assert report.outcome == "done" and "stop rule is met" in report.message
    # Himberg's minimum (1000 frames) decides here; the rule checked each sensor's standard error itself
    assert 1000 <= step.n_frames <= 1050
    se = np.linalg.norm(step.position.std(axis=0, ddof=1), axis=-1) / np.sqrt(step.n_frames)
    assert se.max() <= STATIC_POSITION_SE
    np.testing.assert_array_equal(step.position, position[: step.n_frames])  # every frame as recorded
    assert "standard error" in report.rule and step.attrs["guided_outcome"] == "done"


def test_a_noisy_static_step_does_not_stop_and_is_kept_when_the_source_ends(rng):
    position, quaternion = static_cube(1500, rng, noise=5e-4)  # 0.5 mm jitter: SE 5 µm needs 30,000 frames
    step, report = collect_step(ArraySource(position, quaternion), "cube_calibration")
    assert report.outcome == "kept" and "the source ended" in report.message and step.n_frames == 1500
    assert not all(p.done for p in report.progress)
    rule = StaticRule("cube_calibration")
    rule.update(Frames(np.arange(1500) / 240, np.ones((1500, 8), bool), position, quaternion))
    _, se, turn_se = rule.standard_errors()
    expected = np.linalg.norm(position.std(axis=0, ddof=1), axis=-1) / np.sqrt(1500)
    np.testing.assert_allclose(se, expected, rtol=1e-6)
    assert np.all(turn_se > STATIC_ANGLE_SE)


def test_a_bumped_cube_restarts_the_survey_and_is_not_averaged(rng):
    bump = 60
    position, quaternion = static_cube(600, rng, moves=[(bump, np.array([0.004, 0.0, 0.0]))])
    attrs = {"declared_position": np.array([0.5, 0, 0]), "declared_quaternion": np.array([1.0, 0, 0, 0])}
    statuses = []
    step, report = collect_step(ArraySource(position, quaternion, chunk=25), "cube_survey", attrs=attrs,
                                on_status=statuses.append, status_every_s=0)
    assert report.restarts == 1 and report.dropped_frames == bump
    assert report.outcome == "done" and "restarted 1 time" in report.message
    assert any("the cube moved during the survey" in p for p in report.problems)
    assert any("the cube moved during the survey" in p for s in statuses for p in s.problems)
    # only frames after the bump: their mean is the new placement, not a blend of the two
    np.testing.assert_array_equal(step.position, position[bump : bump + step.n_frames])
    assert 100 <= step.n_frames < 125  # the survey's minimum, counted again from the bump (read every 25 frames)


def test_one_glitching_frame_is_not_a_bump(rng):
    position, quaternion = static_cube(2000, rng)
    position[30, 3] += 0.003  # one frame 3 mm off: beyond the bump bound, and in the mean (SE 5 µm after ~1000)
    step, report = collect_step(ArraySource(position, quaternion), "wand_calibration")
    assert report.restarts == 0 and report.outcome == "done"


def test_a_stale_and_a_missing_sensor_are_named(rng):
    position, quaternion = static_cube(400, rng)
    position[100:, 3] = position[100, 3]  # sensor 3 repeats its pose exactly from frame 100 on
    quaternion[100:, 3] = quaternion[100, 3]
    valid = np.ones((400, 8), bool)
    valid[200:, 5] = False
    statuses = []
    collect_step(ArraySource(position, quaternion, valid), "cube_survey", rule=CountRule("cube_survey", 400),
                 on_status=statuses.append, status_every_s=0)
    last = statuses[-1]
    assert [s.state for s in last.sensors] == ["OK"] * 3 + ["stale"] + ["OK"] + ["missing"] + ["OK"] * 2
    assert "sensor 3 stale for 1.2 s" in last.problems  # frames 100 to 399 at 240 Hz: 1.25 s
    assert "sensor 5 missing for 0.8 s" in last.problems
    assert last.sensors[0].rate_hz == pytest.approx(240.0)


def _sweep_rule(small_session, **kw):
    simulator, session = small_session
    before = Session(session.hemisphere, {k: session.steps[k] for k in ("cube_calibration", "cube_survey",
                                                                        "wand_calibration")})
    return SweepRule(before, **dict(dict(min_kept=1000, per_octant=20, per_direction=5), **kw))


@pytest.fixture(scope="module")
def longer_sweep(small_session):
    """A 12,000-frame sweep (the spiral then turns 7.5 times: every octant of the ball is entered)."""
    simulator, _ = small_session
    return simulator.step("wand_sweep", 12_000)


def test_a_sweep_that_never_enters_one_octant_names_it(small_session, longer_sweep):
    simulator, session = small_session
    rule = _sweep_rule(small_session, per_octant=200, per_direction=20)
    sweep, truth = longer_sweep
    # the declared frame is within millimetres of the truth: octants of the truth are octants of the ball
    offset = truth.position - rule.centre
    outer = np.linalg.norm(offset, axis=-1) >= rule.radius / 2 - 0.03
    octant = (offset[..., 0] > 0) * 4 + (offset[..., 1] > 0) * 2 + (offset[..., 2] > 0)
    avoided = 4 + 0 + 1  # +x -y +z
    keep = ~np.any(outer & (octant == avoided), axis=1)
    assert 0.5 < keep.mean() < 0.95
    source = Unlabelled(SessionSource(Session(session.hemisphere, {"wand_sweep": sweep.select(keep)})))
    with source.source:
        step, report = collect_step(source, "wand_sweep", rule=rule)
    state = rule.state()
    assert not state.done and OCTANT_NAMES[avoided] == "+x -y +z"
    assert state.thin.startswith("the +x -y +z octant of the ball ("), state.thin
    assert rule.octants[avoided] < 0.02 * np.delete(rule.octants, avoided).min()  # grazed at its planes only
    assert report.outcome == "kept" and "the source ended before the stop rule was met" in report.message
    np.testing.assert_array_equal(step.signal, sweep.signal[keep])
    # the whole sweep enters every octant: the same rule's octants are met, and only a direction is thin (the
    # spiral crosses the equator once, short of +x); without the direction target the rule is met
    for per_direction, done in ((20, False), (0, True)):
        whole = _sweep_rule(small_session, per_octant=200, per_direction=per_direction)
        with SessionSource(Session(session.hemisphere, {"wand_sweep": sweep})) as inner:
            step, report = collect_step(Unlabelled(inner), "wand_sweep", rule=whole)
        assert (whole.octants >= 200).all() and whole.state().done == done
        assert report.outcome == ("done" if done else "kept")
        assert whole.state().thin == (None if done else "the wand pointing +x (0 of 20 frames)")
    assert step.n_frames < sweep.n_frames and whole.kept >= 1000
    assert set(whole.dropped) >= {"outside the cube", "residual too high"}


def test_a_wand_out_of_order_breaks_its_rigidity_and_is_said(small_session):
    simulator, session = small_session
    sweep = session.steps["wand_sweep"].select(slice(0, 480))
    position, quaternion = sweep.poses(session.hemisphere)
    words = []
    for order in (list(range(8)), [0, 1, 2, 6, 4, 5, 3, 7]):  # sensors 3 and 6 swapped (a wrong --sensors)
        rule = _sweep_rule(small_session)
        rule.update(Frames(sweep.time, sweep.valid_mask[:, order], position[:, order], quaternion[:, order]))
        rule.finish()
        words.append([p for p in rule.state().problems if "lever arms" in p])
    assert words[0] == []
    assert len(words[1]) == 1 and words[1][0].startswith("wand sensors 3, 6 are up to ")
    arms = rule.model.wand.lever_arms
    stated = float(words[1][0].split("up to ")[1].split(" mm")[0])
    assert abs(stated - 1e3 * abs(arms[6] - arms[3])) < 10  # the swap moves each by the two lever arms' difference


def test_sensor_0_leaving_the_cube_is_said(small_session):
    simulator, session = small_session
    rule = _sweep_rule(small_session, min_kept=10**9)
    sweep = session.steps["wand_sweep"].select(slice(0, 600))
    moved = dataclasses.replace(sweep, signal=None, position=sweep.poses(session.hemisphere)[0] + [0, 0.2, 0],
                                quaternion=sweep.poses(session.hemisphere)[1])
    rule.update(Frames(moved.time, moved.valid_mask, moved.position, moved.quaternion))
    rule.finish()
    assert any(p.startswith("sensor 0 left the cube") for p in rule.state().problems)
    assert rule.kept == 0


@pytest.mark.parametrize("poses_only", [False, True], ids=["signals and poses", "poses only (a PLUS user)"])
def test_a_rehearsal_is_collected_pose_for_pose(small_session, tmp_path, poses_only):
    simulator, session = small_session
    survey = session.steps["cube_survey"]
    output = tmp_path / "rehearsal.h5"
    started = []
    with SessionSource(session, pause_s=2.0, chunk=97, poses_only=poses_only) as source:
        collected, reports = collect_protocol(source, STEPS, output=output, hemisphere=session.hemisphere,
                                              declared_position=survey.attrs["declared_position"],
                                              declared_quaternion=survey.attrs["declared_quaternion"],
                                              on_step_start=lambda step, words: started.append(step))
    assert started == list(STEPS) and [r.outcome for r in reports] == ["done"] * 5
    written = read_session(output)
    for name in STEPS:
        want, got = session.steps[name], written.steps[name]
        assert got.n_frames == want.n_frames, name
        np.testing.assert_allclose(got.time, want.time, atol=1e-9)
        np.testing.assert_array_equal(got.valid_mask, want.valid_mask)
        ok = want.valid_mask
        np.testing.assert_allclose(got.position[ok], want.position[ok], atol=1e-6, rtol=0)
        np.testing.assert_allclose(got.quaternion[ok], want.quaternion[ok], atol=1e-9, rtol=0)
        if poses_only:
            assert got.signal is None
        else:
            np.testing.assert_allclose(got.signal[ok], want.signal[ok], atol=1e-12, rtol=0)
        assert collected.steps[name].n_frames == want.n_frames
    np.testing.assert_array_equal(written.steps["cube_survey"].attrs["declared_position"],
                                  survey.attrs["declared_position"])


def _stop_when(frames):
    stop = threading.Event()

    def on_status(status):
        if status.frames >= frames:
            stop.set()

    return stop, on_status


def test_a_stop_request_keeps_a_usable_step(rng, tmp_path):
    position, quaternion = static_cube(5000, rng, noise=5e-4)  # never meets its standard-error bound
    stop, on_status = _stop_when(1200)
    output = tmp_path / "s.h5"
    session, reports = collect_protocol(ArraySource(position, quaternion), ["cube_calibration"], output=output,
                                        on_status=on_status, stop=stop, status_every_s=0)
    (report,) = reports
    assert report.stopped and report.outcome == "kept" and "kept as a valid step" in report.message
    assert read_session(output).steps["cube_calibration"].n_frames == report.frames >= 1200
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.h5"]


def test_ctrl_c_drops_a_step_too_short_to_use_and_writes_nothing(rng, tmp_path):
    position, quaternion = static_cube(5000, rng)
    output = tmp_path / "s.h5"
    source = ArraySource(position, quaternion, interrupt_at=7)  # Ctrl-C on the 7th read: 300 frames recorded
    session, reports = collect_protocol(source, ["cube_calibration", "wand_calibration"], output=output)
    (report,) = reports  # the walk ends at the stopped step
    assert report.stopped and report.outcome == "dropped" and report.frames == 300
    assert "dropped, nothing kept" in report.message and "needs 1000" in report.message
    assert list(tmp_path.iterdir()) == [] and not session.steps


def test_ctrl_c_after_earlier_steps_keeps_them_in_the_file(small_session, tmp_path):
    simulator, session = small_session
    output = tmp_path / "s.h5"
    cube = session.steps["cube_calibration"]
    source = SourceFeed(Unlabelled(SessionSource(Session(session.hemisphere, {"cube_calibration": cube}))))
    source.source.source.open()
    collect_protocol(source, ["cube_calibration"], output=output)
    wand = session.steps["wand_calibration"]
    position, quaternion = wand.poses(session.hemisphere)
    interrupted = ArraySource(np.repeat(position[:1], 500, 0), np.repeat(quaternion[:1], 500, 0), interrupt_at=2)
    _, reports = collect_protocol(interrupted, ["wand_calibration"], output=output)
    assert reports[0].outcome == "dropped"
    assert set(read_session(output).steps) == {"cube_calibration"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.h5"]


def test_a_cube_step_refuses_a_source_with_the_wrong_sensor_count(rng):
    position, quaternion = static_cube(100, rng)
    with pytest.raises(InputError, match="cube_calibration records 8 sensors but the source sends 4"):
        collect_step(ArraySource(position[:, :4], quaternion[:, :4]), "cube_calibration")


def test_source_events_reach_the_report(rng):
    position, quaternion = static_cube(1200, rng)

    class Dropping(ArraySource):
        def read(self, timeout_s):
            out = super().read(timeout_s)
            if self.reads == 3:
                out.insert(0, SourceEvent("disconnected", "the connection dropped; reconnecting"))
            return out

    step, report = collect_step(Dropping(position, quaternion), "cube_calibration")
    assert "the connection dropped; reconnecting" in report.problems
    assert any(e.kind == "disconnected" for e in report.events) and report.outcome == "done"


def test_check_and_count_rules_stop_by_frames_or_tracker_time(rng):
    position, quaternion = static_cube(1000, rng)
    step, report = collect_step(ArraySource(position[:, :1], quaternion[:, :1]), "check", frames=333)
    assert step.n_frames == 350 and report.outcome == "done"  # the rule is read after each batch of 50
    step, _ = collect_step(ArraySource(position[:, :1], quaternion[:, :1], chunk=1), "check", duration_s=1.0)
    assert step.n_frames == 241 and isinstance(step, Step)


def test_a_source_that_fails_for_good_ends_the_step_keeping_what_is_usable(rng):
    from ivc.errors import LiveError

    position, quaternion = static_cube(5000, rng, noise=5e-4)

    class Failing(ArraySource):
        def read(self, timeout_s):
            if self.reads >= self.fail_after:
                raise LiveError("igtl://h:1: the connection was lost and 5 reconnections failed")
            return super().read(timeout_s)

    for fail_after, outcome in ((30, "kept"), (5, "dropped")):  # 1500 frames recorded, or 250
        source = Failing(position, quaternion)
        source.fail_after = fail_after
        step, report = collect_step(source, "cube_calibration")
        assert report.outcome == outcome and "the source failed (igtl://h:1: the connection was lost" in report.message
        assert (step is None) == (outcome == "dropped")


def test_a_rehearsal_step_ends_when_its_source_falls_silent(small_session):
    """A rehearsal over a network never says it finished: its last step ends when nothing more comes."""
    simulator, session = small_session

    class Silent:
        def __init__(self, inner):
            self.inner, self.sensor_names, self.sample_rate_hz = inner, inner.sensor_names, inner.sample_rate_hz

        def read(self, timeout_s):
            return self.inner.read(timeout_s)

    with SessionSource(Session(session.hemisphere, {"check": session.steps["check"]})) as inner:
        step, report = collect_step(Silent(inner), "check", idle_limit_s=0.0)
    assert report.outcome == "done" and step.n_frames == session.steps["check"].n_frames


def test_an_extension_sweep_reports_the_working_volume_by_face(rng):
    from ivc.collect.rules import ExtensionRule

    session = Session(attrs={"working_volume_center": np.array([0.5, 0.0, 0.0]),
                             "working_volume_size": np.array([0.4, 0.4, 0.4])})
    rule = ExtensionRule(session)
    assert "declared working volume (400 x 400 x 400 mm)" in rule.description
    # a wand walked through the -x half of the box only
    points = np.array([0.3, -0.2, -0.2]) + rng.random((20_000, 8, 3)) * np.array([0.2, 0.4, 0.4])
    identity = np.tile([1.0, 0, 0, 0], (20_000, 8, 1))
    frames = Frames(np.arange(20_000) / 240, np.ones((20_000, 8), bool), points, identity)
    rule.update(frames)
    share, faces = rule.shares()
    assert 0.5 <= share < 0.62  # the half, and the lattice within reach (4 cm) beyond it
    assert faces["-x"] == 1.0 and faces["+x"] == 0.0 and 0.5 < faces["+y"] < 0.65
    state = rule.state()
    assert not state.done and state.thin == "face +x of the working volume (0 % covered)"
    assert state.target[0] > 0.5 and len(state.cells) == 6
    rule.update(Frames(frames.time, frames.valid, points + [0.2, 0, 0], frames.quaternion))
    assert rule.state().done and rule.state().thin is None


def test_an_extension_sweep_without_a_declared_volume_says_so():
    from ivc.collect.rules import ExtensionRule

    rule = ExtensionRule(Session())
    assert "declares no working volume" in rule.description
    assert rule.state().problems == ["no declared working volume: coverage cannot be stated"]


def test_a_signal_only_source_is_watched_through_the_closed_form_pose(small_session):
    simulator, session = small_session
    cube = session.steps["cube_calibration"]
    signals = dataclasses.replace(cube, position=None, quaternion=None)
    with SessionSource(Session(session.hemisphere, {"cube_calibration": signals})) as inner:
        step, report = collect_step(Unlabelled(inner), "cube_calibration")
    assert step.position is None and step.n_frames == cube.n_frames
    np.testing.assert_array_equal(step.signal[step.valid_mask], cube.signal[cube.valid_mask])
    assert report.progress[1].value < 1e3 * STATIC_POSITION_SE  # the closed-form poses' standard error, mm
