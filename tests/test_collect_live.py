"""`ivc collect STEP|protocol --source igtl://...|polhemus:...` (issue 36, item 4): the CLI's guided path, end to
end, against live sources registered in place of the real ones (the registry's interface, not a network)."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from ivc.cli import cli
from ivc.collect import sources
from ivc.session import STEPS, write
from ivc.session import read as read_session
from tests.live_helpers import ArraySource, static_cube


class FakeLive:
    """Stands for ``igtl://`` in the registry: ``from_spec`` records its arguments and returns the source the test
    put in :attr:`NEXT` (an unlabelled source: a real tracker's kind)."""

    NEXT = None
    SPECS: list = []

    @classmethod
    def from_spec(cls, argument, *, sensors=None, hemisphere="+x"):
        cls.SPECS.append((argument, sensors, hemisphere))
        return cls.NEXT


class Opened:
    """A source usable as a context manager, as the CLI uses it."""

    def __init__(self, source):
        self.source = source
        self.sensor_names, self.sample_rate_hz = source.sensor_names, source.sample_rate_hz

    def read(self, timeout_s):
        return self.source.read(timeout_s)

    @property
    def finished(self):
        return self.source.finished

    def __enter__(self):
        if hasattr(self.source, "open"):
            self.source.open()
        return self

    def __exit__(self, *exc):
        pass


@pytest.fixture
def live(monkeypatch):
    monkeypatch.setitem(sources.LIVE_SOURCES, "igtl://", ("tests.test_collect_live", "FakeLive"))
    FakeLive.SPECS = []
    return FakeLive


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def test_a_static_step_from_a_live_source_stops_by_its_rule(live, rng, tmp_path):
    position, quaternion = static_cube(3000, rng)
    names = [f"tool{k}" for k in range(8)]
    live.NEXT = Opened(ArraySource(position, quaternion, names=names))
    output = tmp_path / "s.h5"
    result = run("collect", "cube_calibration", "--source", "igtl://localhost:18944", "-o", output, "--sensors",
                 ",".join(names))
    assert result.exit_code == 0, result.output
    assert live.SPECS == [("localhost:18944", names, "+x")]
    assert "rule: cube_calibration: stops when every sensor's mean pose has a standard error" in result.output
    assert "cube_calibration: done, the stop rule is met after 1,000 frames" in result.output
    step = read_session(output).steps["cube_calibration"]
    assert step.n_frames == 1000 and step.names == names
    np.testing.assert_array_equal(step.position, position[:1000])
    # the step is there: again without --force is refused, and nothing changes
    result = run("collect", "cube_calibration", "--source", "igtl://localhost:18944", "-o", output)
    assert result.exit_code == 1 and "already recorded; pass --force" in result.output


def test_frames_or_duration_replace_the_rule(live, rng, tmp_path):
    position, quaternion = static_cube(2000, rng)
    output = tmp_path / "s.h5"
    live.NEXT = Opened(ArraySource(position[:, :1], quaternion[:, :1]))
    result = run("collect", "check", "--source", "igtl://h:1", "-o", output, "--frames", 500)
    assert result.exit_code == 0, result.output
    assert read_session(output).steps["check"].n_frames == 500
    live.NEXT = Opened(ArraySource(position[:, :1], quaternion[:, :1], chunk=1))
    result = run("collect", "check", "--source", "igtl://h:1", "-o", output, "--duration", 2, "--force")
    assert result.exit_code == 0, result.output
    assert read_session(output).steps["check"].n_frames == 481  # 2 s at 240 Hz, from the first frame's time


def test_ctrl_c_drops_a_short_step_and_exits_non_zero(live, rng, tmp_path):
    position, quaternion = static_cube(3000, rng)
    live.NEXT = Opened(ArraySource(position, quaternion, interrupt_at=4))
    output = tmp_path / "s.h5"
    result = run("collect", "cube_calibration", "--source", "igtl://h:1", "-o", output)
    assert result.exit_code == 1
    assert "stopped before its stop rule was met; dropped, nothing kept" in result.output
    assert list(tmp_path.iterdir()) == []


def test_the_survey_needs_its_declared_pose(live, rng, tmp_path):
    live.NEXT = Opened(ArraySource(*static_cube(300, rng)))
    result = run("collect", "cube_survey", "--source", "igtl://h:1", "-o", tmp_path / "s.h5")
    assert result.exit_code == 2 and "needs the cube's declared pose" in result.output
    result = run("collect", "cube_survey", "--source", "igtl://h:1", "-o", tmp_path / "s.h5",
                 "--declared-position", "0.5,0,0", "--declared-quaternion", "1,0,0,0")
    assert result.exit_code == 0, result.output
    survey = read_session(tmp_path / "s.h5").steps["cube_survey"]
    np.testing.assert_array_equal(survey.attrs["declared_position"], [0.5, 0, 0])


def test_live_only_options_are_refused_for_the_simulator(tmp_path):
    result = run("collect", "check", "--source", "sim", "-o", tmp_path / "s.h5", "--duration", 3)
    assert result.exit_code == 2 and "for live sources" in result.output


def test_the_guided_protocol_reproduces_a_replayed_session(small_session, tmp_path):
    simulator, session = small_session
    recorded = tmp_path / "recorded.h5"
    write(session, recorded)
    survey = session.steps["cube_survey"].attrs
    output = tmp_path / "guided.h5"
    result = run("collect", "protocol", "--source", f"replay:{recorded}", "--guided", "-o", output,
                 "--declared-position", ",".join(repr(float(v)) for v in survey["declared_position"]),
                 "--declared-quaternion", ",".join(repr(float(v)) for v in survey["declared_quaternion"]))
    assert result.exit_code == 0, result.output
    for name in STEPS:
        assert f"== {name}: " in result.output
        assert f"{name}: recorded the {session.steps[name].n_frames:,} frames the source labelled {name}" in \
            result.output
    written = read_session(output)
    for name in STEPS:
        ok = session.steps[name].valid_mask
        np.testing.assert_allclose(written.steps[name].position[ok], session.steps[name].position[ok], atol=1e-6)


def test_the_guided_protocol_from_an_unlabelled_live_source(live, small_session, tmp_path):
    """A tracker that labels nothing: each step ends by its own rule (a count here), and the next step starts with
    the frames that follow; the person's 100 frames of each step are recorded as that step."""
    simulator, session = small_session

    class Steps:
        """The first 100 frames of each step's poses, one step after the other, through one source."""

        sensor_names, sample_rate_hz = (), 240.0

        def __init__(self):
            self.parts = []
            for name in STEPS:
                step = session.steps[name].select(slice(0, 100))
                self.parts.append(ArraySource(*step.poses(session.hemisphere), step.valid_mask, chunk=100))

        def read(self, timeout_s):
            while self.parts and self.parts[0].finished:
                self.parts.pop(0)
            return self.parts[0].read(timeout_s) if self.parts else []

        @property
        def finished(self):
            return all(p.finished for p in self.parts)

    live.NEXT = Opened(Steps())
    survey = session.steps["cube_survey"].attrs
    output = tmp_path / "s.h5"
    result = run("collect", "protocol", "--source", "igtl://h:1", "-o", output, "--frames", 100,
                 "--declared-position", ",".join(repr(float(v)) for v in survey["declared_position"]),
                 "--declared-quaternion", ",".join(repr(float(v)) for v in survey["declared_quaternion"]))
    assert result.exit_code == 0, result.output
    written = read_session(output)
    for name in STEPS:
        assert f"{name}: done, the stop rule is met after 100 frames" in result.output
        want = session.steps[name].select(slice(0, 100))
        ok = want.valid_mask
        np.testing.assert_array_equal(written.steps[name].valid_mask, ok)
        np.testing.assert_allclose(written.steps[name].position[ok], want.position[ok], atol=1e-12)


def test_the_terminal_views_show_sensors_progress_and_problems(rng):
    import io

    from rich.console import Console

    from ivc.cli.guided_view import PlainView, RichView
    from ivc.collect.guide import collect_step

    position, quaternion = static_cube(600, rng)
    position[200:, 3] = position[200, 3]  # sensor 3 stale
    quaternion[200:, 3] = quaternion[200, 3]
    out = io.StringIO()
    rich = RichView(Console(file=out, force_terminal=True, width=120))
    plain_out = io.StringIO()
    plain = PlainView(plain_out)
    statuses = []
    step, report = collect_step(ArraySource(position, quaternion), "cube_calibration", on_status=statuses.append,
                                status_every_s=0)
    for view in (rich, plain):
        view.on_step_start("cube_calibration", "Put the cube in free space.")
        for status in statuses:
            view(status)
        view.on_step(step, report)
        view.close()
    text = out.getvalue()
    for words in ("sensor", "state", "rate (Hz)", "jitter (ms)", "stale", "frames since still",
                  "problem: sensor 3 stale for", "cube_calibration: the source ended"):
        assert words in text, words
    lines = plain_out.getvalue().splitlines()
    assert lines[0] == "== cube_calibration: Put the cube in free space."
    assert lines[1].startswith("rule: cube_calibration: stops when")
    assert sum("problem: sensor 3 stale for" in line for line in lines) == 1  # once, not at every status
    assert lines[-1] == report.message


def test_view_serves_the_step_on_loopback(live, rng, tmp_path):
    pytest.importorskip("viser")
    live.NEXT = Opened(ArraySource(*static_cube(1500, rng)))
    result = run("collect", "wand_calibration", "--source", "igtl://h:1", "-o", tmp_path / "s.h5", "--view",
                 "--view-port", 0)
    assert result.exit_code == 0, result.output
    assert "3D view: http://127.0.0.1:" in result.output
    assert read_session(tmp_path / "s.h5").steps["wand_calibration"].n_frames == 100


def test_a_bumped_survey_through_the_polhemus_source_and_its_emulator(rng):
    """The guide over the real serial source (ivc.collect.polhemus_serial) and the emulated Liberty on a
    pseudo-terminal (the serial source's own test emulator): the bump is caught and the survey restarted."""
    serial = pytest.importorskip("ivc.collect.polhemus_serial")
    emulator = pytest.importorskip("tests.polhemus_emulator")
    from ivc.collect.guide import collect_step

    position, quaternion = static_cube(3000, rng, moves=[(50, np.array([0.004, 0.0, 0.0]))])
    attrs = {"declared_position": np.array([0.5, 0, 0]), "declared_quaternion": np.array([1.0, 0, 0, 0])}
    with emulator.PolhemusEmulator(position, quaternion, model="liberty") as tracker:
        with serial.PolhemusSource(tracker.path) as source:
            step, report = collect_step(source, "cube_survey", attrs=attrs, idle_limit_s=60)
    assert report.outcome == "done" and report.restarts == 1 and 50 <= report.dropped_frames <= 53
    assert any("the cube moved during the survey" in p for p in report.problems)
    start = report.dropped_frames  # every frame streamed (the tracker's frame count), so frame k is truth frame k
    np.testing.assert_allclose(step.position, position[start : start + step.n_frames], atol=1e-6)  # float32 in cm
