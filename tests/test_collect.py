"""`ivc collect`: simulated and replayed recordings, checks, and the CSV format."""

import hashlib

import numpy as np
import pytest
from click.testing import CliRunner

from ivc import rotations, session
from ivc.cli import cli
from ivc.collect import CsvError, check_step, read_csv, write_csv

SMALL_SCENE = """
name = "small"
[cube]
center = [0.5, 0.0, 0.0]
[[conductor]]
shape = "plate"
size = [0.6, 0.6]
position = [0.5, 0.0, -0.35]
material = "aluminium"
resolution_mm = 100
"""


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "small.toml"
    path.write_text(SMALL_SCENE)
    return path


def run(*args):
    result = CliRunner().invoke(cli, [str(a) for a in args])
    return result


def digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def collect_protocol(scene_file, out, seed=0):
    return run("collect", "protocol", "--source", f"sim:{scene_file}", "-o", out, "--seed", seed,
               "--sweep-frames", 2000, "--check-frames", 300)


def test_protocol_writes_every_step_and_is_reproducible(tmp_path, scene_file):
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    result = collect_protocol(scene_file, a)
    assert result.exit_code == 0, result.output
    assert "wand_sweep: 2000 frames x 8 sensors" in result.output
    s = session.read(a)
    assert list(s.steps) == list(session.STEPS)
    assert s.missing_for_fit() == []
    assert set(s.truth) == set(session.STEPS)
    assert collect_protocol(scene_file, b).exit_code == 0
    assert digest(a) == digest(b)
    # refuses to replace an existing file without --force
    result = collect_protocol(scene_file, a, seed=1)
    assert result.exit_code == 1 and "--force" in result.output
    assert digest(a) == digest(b)


def test_single_steps_build_a_session(tmp_path, scene_file):
    out = tmp_path / "s.h5"
    result = run("collect", "cube_survey", "--source", f"sim:{scene_file}", "-o", out, "--frames", 150)
    assert result.exit_code == 0, result.output
    assert "recorded before cube_calibration" in result.output  # order warning, step still written
    result = run("collect", "cube_calibration", "--source", f"sim:{scene_file}", "-o", out, "--frames", 200)
    assert "at least 1000" in result.output
    before = digest(out)
    result = run("collect", "cube_calibration", "--source", f"sim:{scene_file}", "-o", out, "--frames", 1000)
    assert result.exit_code == 1 and "already recorded" in result.output and digest(out) == before
    result = run("collect", "cube_calibration", "--source", f"sim:{scene_file}", "-o", out, "--frames", 1000, "--force")
    assert result.exit_code == 0
    assert session.read(out).steps["cube_calibration"].n_frames == 1000


def test_replayed_csv_equals_replayed_session(tmp_path, scene_file):
    recording = tmp_path / "recording.h5"
    assert collect_protocol(scene_file, recording).exit_code == 0
    original = session.read(recording)
    for name in ("cube_survey", "wand_sweep"):
        write_csv(original.steps[name], tmp_path / f"{name}.csv")
    declared = original.steps["cube_survey"].attrs
    position = ",".join(repr(float(v)) for v in declared["declared_position"])
    quaternion = ",".join(repr(float(v)) for v in declared["declared_quaternion"])
    from_csv, from_h5 = tmp_path / "csv.h5", tmp_path / "h5.h5"
    for out, source in ((from_csv, "csv"), (from_h5, "h5")):
        for name in ("cube_survey", "wand_sweep"):
            file = tmp_path / f"{name}.csv" if source == "csv" else recording
            extra = ["--declared-position", position, "--declared-quaternion", quaternion] if source == "csv" and \
                name == "cube_survey" else []
            result = run("collect", name, "--source", f"replay:{file}", "-o", out, *extra)
            assert result.exit_code == 0, result.output
    a, b = session.read(from_csv), session.read(from_h5)
    for name in ("cube_survey", "wand_sweep"):
        sa, sb = a.steps[name], b.steps[name]
        for dataset in ("time", "signal", "position", "quaternion", "valid"):
            assert getattr(sa, dataset).tobytes() == getattr(sb, dataset).tobytes(), (name, dataset)
        assert sa.sensor_ids == sb.sensor_ids and sa.sample_rate_hz == sb.sample_rate_hz
        assert sa.description == sb.description
        for key in sa.attrs:
            np.testing.assert_array_equal(sa.attrs[key], sb.attrs[key])


def test_malformed_csv_reports_lines_and_writes_nothing(tmp_path):
    rows = [
        "time,sensor,x,y,z,qw,qx,qy,qz,valid",
        "0.0,a,0.5,0,0,1,0,0,0,1",
        "0.0,b,0.5,0.1,0,1,0,0,0,1",
        "0.1,a,0.5,zero,0,1,0,0,0,1",
        "0.1,b,0.5,0.1,0,1,0,0,1",
        "0.2,a,0.5,0,0,1,0,0,0,maybe",
        "0.2,b,nan,0.1,0,1,0,0,0,1",
    ]
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(CsvError) as error:
        read_csv(path)
    message = str(error.value)
    for line in ("line 4: y = 'zero'", "line 5: 9 fields", "line 6: valid = 'maybe'", "line 7: NaN"):
        assert line in message
    out = tmp_path / "out.h5"
    result = run("collect", "check", "--source", f"replay:{path}", "-o", out)
    assert result.exit_code == 1 and "line 4" in result.output
    assert not out.exists()


def test_csv_structure_errors(tmp_path):
    path = tmp_path / "x.csv"
    path.write_text("time,sensor,x,y,z\n0,a,1,2,3\n")
    with pytest.raises(CsvError, match="line 1: the header needs"):
        read_csv(path)
    path.write_text("time,sensor,x,y,z,qw,qx,qy,qz\n0,a,.5,0,0,1,0,0,0\n0,b,.5,0,0,1,0,0,0\n1,b,.5,0,0,1,0,0,0\n"
                    "1,a,.5,0,0,1,0,0,0\n")
    with pytest.raises(CsvError, match="line 4: sensor 'b' where 'a' was expected"):
        read_csv(path)


def test_survey_replay_needs_a_declared_pose(tmp_path):
    path = tmp_path / "survey.csv"
    lines = ["time,sensor,x,y,z,qw,qx,qy,qz"]
    for frame in range(3):
        lines += [f"{frame / 240!r},s{n},0.5,{n * 0.01},0,1,0,0,0" for n in range(8)]
    path.write_text("\n".join(lines) + "\n")
    result = run("collect", "cube_survey", "--source", f"replay:{path}", "-o", tmp_path / "o.h5")
    assert result.exit_code != 0 and "--declared-position" in result.output
    result = run("collect", "cube_survey", "--source", f"replay:{path}", "-o", tmp_path / "o.h5",
                 "--declared-position", "0.5,0,0", "--declared-quaternion", "1,0,0,0")
    assert result.exit_code == 0, result.output


def test_static_check_notices_a_moving_fixture():
    frames = 200
    position = np.tile([0.5, 0.0, 0.0], (frames, 8, 1))
    position[:, 3, 0] += np.linspace(0, 0.01, frames)  # one sensor slides 10 mm
    quaternion = np.tile([1.0, 0, 0, 0], (frames, 8, 1))
    step = session.Step(time=np.arange(frames) / 240, position=position, quaternion=quaternion)
    warnings = check_step("cube_survey", step)
    assert any("not static" in w and "sensor 3" in w for w in warnings)
    still = session.Step(time=np.arange(frames) / 240, position=np.tile([0.5, 0, 0.0], (frames, 8, 1)),
                         quaternion=quaternion)
    assert not any("not static" in w for w in check_step("cube_survey", still))


def test_unknown_source_is_explained(tmp_path):
    result = run("collect", "check", "--source", "tracker", "-o", tmp_path / "x.h5")
    assert result.exit_code == 2 and "replay:FILE" in result.output
    result = run("collect", "check", "--source", "sim:nowhere", "-o", tmp_path / "x.h5")
    assert result.exit_code == 1 and "built-in scenes are" in result.output


def test_csv_in_tracker_units_reads_as_metres_and_quaternions(tmp_path):
    """A Polhemus-style recording (ms, inches, az/el/roll degrees) reads as the same poses in s, m and quaternions."""
    rng = np.random.default_rng(5)
    F, names = 6, ["a", "b"]
    time = np.arange(F) / 240.0
    position = rng.uniform(0.2, 0.6, (F, 2, 3))
    angles = np.column_stack([rng.uniform(-180, 180, 2 * F), rng.uniform(-89, 89, 2 * F),
                              rng.uniform(-180, 180, 2 * F)])
    lines = ["time_ms,sensor,x_in,y_in,z_in,az,el,roll,valid"]
    for k in range(F):
        for s, name in enumerate(names):
            xyz = position[k, s] / 0.0254
            numbers = [time[k] * 1e3, *xyz, *angles[2 * k + s]]
            lines.append(",".join([repr(float(numbers[0])), name, *(repr(float(v)) for v in numbers[1:]), "1"]))
    path = tmp_path / "polhemus.csv"
    path.write_text("\n".join(lines) + "\n")
    step = read_csv(path)
    assert step.sample_rate_hz == 240.0
    np.testing.assert_allclose(step.time, time, atol=1e-15)
    np.testing.assert_allclose(step.position, position, atol=1e-14)
    # Polhemus's direction cosines: the sensor's x axis is (cos az cos el, sin az cos el, −sin el) in the source
    # frame, its y axis (cos az sin el sin roll − sin az cos roll, sin az sin el sin roll + cos az cos roll,
    # cos el sin roll)
    a, e, r = np.radians(angles).T
    x_axis = np.column_stack([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), -np.sin(e)])
    y_axis = np.column_stack([np.cos(a) * np.sin(e) * np.sin(r) - np.sin(a) * np.cos(r),
                              np.sin(a) * np.sin(e) * np.sin(r) + np.cos(a) * np.cos(r), np.cos(e) * np.sin(r)])
    T = rotations.to_matrix(step.quaternion).reshape(-1, 3, 3)
    np.testing.assert_allclose(T[:, :, 0], x_axis, atol=1e-12)
    np.testing.assert_allclose(T[:, :, 1], y_axis, atol=1e-12)


def test_csv_header_and_unit_errors(tmp_path):
    path = tmp_path / "x.csv"
    path.write_text("time,time_ms,sensor,x,y,z,qw,qx,qy,qz\n0,0,a,.5,0,0,1,0,0,0\n")
    with pytest.raises(CsvError, match="one time column"):
        read_csv(path)
    path.write_text("time,sensor,x,y,z,qw,qx,qy,qz,az,el,roll\n0,a,.5,0,0,1,0,0,0,0,0,0\n")
    with pytest.raises(CsvError, match="not both"):
        read_csv(path)
    # a Polhemus reports inches: 20 inches read as metres is far beyond an AC tracker's reach
    path.write_text("time,sensor,x,y,z,qw,qx,qy,qz\n0,a,20,3,-4,1,0,0,0\n0.01,a,21,3,-4,1,0,0,0\n")
    with pytest.raises(CsvError, match="median distance from the source is 21.1 m.*x_in"):
        read_csv(path)
    out = tmp_path / "out.h5"
    result = run("collect", "check", "--source", f"replay:{path}", "-o", out)
    assert result.exit_code == 1 and "x_in" in result.output and not out.exists()
