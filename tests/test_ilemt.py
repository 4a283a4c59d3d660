"""The ILEMT reader and ``ivc tracker`` on ILEMT's recordings (skipped without ../shared/data) and on a
synthetic recording written in the same format."""

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ivc.cli import cli
from ivc.collect.ilemt import (
    OPTIONS_FILE,
    SOURCE_SIGN_FIXES,
    compensate_stage,
    fixture_rotation,
    parse_sign_fix,
    read_ilemt,
    stack,
)
from ivc.dipole.tracker import Tracker, load_tracker
from ivc.errors import CsvError, InputError
from ivc.pose.calibrate import Fixtures, calibrate, rigid_transform
from ivc.sim.stage import stage_recording

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "ilemt" / "cal_9_15_premo_cmu"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data/ilemt is not here")


def _file(name):
    return DATA / name


@needs_data
def test_frame_counts_and_home_rows():
    md = read_ilemt(_file("soYoutZup_seYoutZup_md.dat"))
    ld = read_ilemt(_file("soYoutZup_seYoutZup_ld.dat"))
    # md: 3x3x3 grid x 5 turns (plus a few extra points) = 142 rows; ld: 5x5x5 x 5 = 625 + 7 = 632
    assert (md.n_points, ld.n_points) == (142, 632)
    assert sorted(np.unique(md.stage[:, 5])) == [-90.0, -45.0, 0.0, 45.0, 90.0]
    assert np.all(md.stage[:, 3:5] == 0) and np.all(ld.stage[:, 3:5] == 0)  # only Rz moves
    for rec in (md, ld):
        assert rec.home[0] and rec.home[-1]  # first and last rows are home: the drift check
        assert 1e-5 < rec.drift < 1e-3  # README: drift 1e-4 to 1e-3 relative
        np.testing.assert_array_equal(rec.J_st[0], np.eye(4))  # home, home sensor fixture
        np.testing.assert_array_equal(rec.stage_compensated[rec.home], rec.stage[rec.home])
    assert np.abs(ld.stage_compensated - ld.stage).max() < 0.5  # stage errors are tenths of a mm


@needs_data
def test_complex_to_real_convention():
    path = _file("soYoutZup_seYoutZup_md.dat")
    first = path.read_text().splitlines()[0].split("\t")
    raw = [complex(v.replace("i", "j")) for v in first[6:15]]
    rec = read_ilemt(path)
    # value k of the row is C[k % 3, k // 3] = C(source, sensor); the signal is Cᵀ (row = sensor coil)
    for k, value in enumerate(raw):
        assert rec.coupling[0, k % 3, k // 3] == value
        assert rec.signal[0, k // 3, k % 3] == pytest.approx(np.sign(value.real) * abs(value), rel=1e-15)
    # README: median |Im C| / |C| about 5e-3 on the high carrier and 1e-3 on the low one
    high = np.median(np.abs(rec.coupling.imag) / np.abs(rec.coupling))
    low_rec = read_ilemt(path, carrier="low")
    low = np.median(np.abs(low_rec.coupling.imag) / np.abs(low_rec.coupling))
    assert 2e-3 < high < 1e-2 and 2e-4 < low < 4e-3
    # README: the low band reads about 30x weaker
    ratio = np.median(np.linalg.norm(rec.signal, axis=(1, 2)) / np.linalg.norm(low_rec.signal, axis=(1, 2)))
    assert 25 < ratio < 40


@needs_data
def test_source_sign_fixes():
    path = _file("soZoutYup_seYoutZup_md.dat")
    raw = complex(path.read_text().split("\t")[6].replace("i", "j"))
    assert np.all(read_ilemt(path).source_signs == 1)  # no fix unless told
    fixed = read_ilemt(path, sign_fixes=SOURCE_SIGN_FIXES)
    np.testing.assert_array_equal(fixed.source_signs, [-1, -1, 1])
    assert fixed.coupling[0, 0, 0] == -raw
    plain = read_ilemt(path)
    np.testing.assert_array_equal(plain.coupling[:, :2], -fixed.coupling[:, :2])
    np.testing.assert_array_equal(plain.coupling[:, 2], fixed.coupling[:, 2])
    assert np.all(read_ilemt(_file("soZoutYup_seYoutZup_source.dat"), sign_fixes=SOURCE_SIGN_FIXES).source_signs == 1)


@needs_data
@pytest.mark.slow
def test_the_concentric_sets_sign_fixes_are_found_in_its_data():
    """Read as recorded, the md files of every source fixturing: exactly the authors' two md fixes are found."""
    from ivc.pose.coil_signs import find_sign_flips

    names = ["soYoutZup_seYoutZup_md.dat", "soZoutYup_seYoutZup_md.dat", "soXoutZup_seYoutZup_md.dat",
             "soXinYup_seYoutZup_md.dat"]
    S, J_so, J_st, index = stack([read_ilemt(_file(n)) for n in names])
    found = {names[f.group]: f.signs.tolist() for f in find_sign_flips(S, J_so, J_st, index)}
    assert found == {"soZoutYup_seYoutZup_md.dat": [-1, -1, 1], "soXoutZup_seYoutZup_md.dat": [-1, -1, 1]}


@needs_data
def test_calibration_on_md_matches_the_authors_residue():
    recs = [read_ilemt(_file(f"soYoutZup_se{se}_md.dat")) for se in ("YoutZup", "ZinYup", "ZinXdown")]
    S, J_so, J_st, index = stack(recs)
    assert len(S) == 426 and np.array_equal(np.bincount(index), [142, 142, 142])
    one = calibrate(S, J_so, J_st, offsets=False, output_correction=False)
    offsets = calibrate(S, J_so, J_st, offsets=True, output_correction=False)
    # README: about 0.7 % with one centre, about 0.5 % with per-coil offsets
    assert 0.6e-2 < np.sqrt(np.mean(one.residue**2)) < 0.8e-2
    assert 0.4e-2 < np.sqrt(np.mean(offsets.residue**2)) < 0.55e-2


def test_fixture_codes():
    for code in ("YoutZup", "ZinYup", "ZinXdown", "XoutZup", "ZoutYup", "XinYup"):
        R = fixture_rotation(code)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-15)
        assert np.linalg.det(R) == pytest.approx(1.0)
    # test_plans.txt's example: ZoutYup takes fixture x, y, z to mover -x, +z, +y
    np.testing.assert_array_equal(fixture_rotation("ZoutYup"), [[-1, 0, 0], [0, 0, 1], [0, 1, 0]])
    np.testing.assert_array_equal(fixture_rotation("YoutZup"), np.eye(3))
    with pytest.raises(InputError, match="unknown ILEMT fixture"):
        fixture_rotation("QoutZup")


def test_stage_compensation_is_zero_at_home_and_turns_with_rz():
    stage = np.array([[0, 0, 0, 0, 0, 0], [50, 0, 0, 0, 0, 0], [50, 0, 0, 0, 0, 90.0]])
    out = compensate_stage(stage)
    np.testing.assert_array_equal(out[0], stage[0])
    dx = out[1, 0] - 50
    assert dx == pytest.approx(-0.040)  # the X table: 0.040 mm error at 0, none at +50
    assert out[2, 0] - 50 == pytest.approx(0.0, abs=1e-15) and out[2, 1] == pytest.approx(dx)


def _write_dat(path, stage, S):
    """An ILEMT-format file: stage poses, then C = Sᵀ column-major, small quadrature parts, low = high / 30."""
    C = np.swapaxes(S, 1, 2)
    with open(path, "w") as out:
        for row, c in zip(stage, C, strict=True):
            values = c.T.reshape(-1)  # column-major: value k is C[k % 3, k // 3]
            high = [f"{v:+.9f}{1e-3 * v:+.9f}i" for v in values]
            low = [f"{v / 30:+.9f}{1e-4 * v:+.9f}i" for v in values]
            out.write("\t".join([f"{x:.5f}" for x in row] + high + low) + "\n")


def _synthetic_recordings(tmp_path, rng):
    truth = Tracker(np.diag([-0.9, 0.5, -0.6]) + 0.02 * rng.standard_normal((3, 3)),
                    np.eye(3) + 0.02 * rng.standard_normal((3, 3)), 1e-3 * rng.standard_normal((3, 3)),
                    5e-4 * rng.standard_normal((3, 3)))
    fixtures = Fixtures(stage=rigid_transform(t=np.array([0.002, 0.24, 0.003])))
    grid = [-40.0, 0.0, 40.0]
    stage = np.array([(0, 0, 0, 0, 0, 0)] + [(x, y, z, 0, 0, rz) for rz in (-90, 0, 90) for z in grid
                                              for y in grid for x in grid] + [(0, 0, 0, 0, 0, 0)], dtype=float)
    paths = []
    for code in ("YoutZup", "ZinYup", "ZinXdown"):
        path = tmp_path / f"soYoutZup_se{code}_md.dat"
        from ivc.collect.ilemt import stage_transforms

        J_st = stage_transforms(compensate_stage(stage), code)
        S = stage_recording(truth, fixtures, np.eye(4), J_st, noise_relative=1e-5, rng=rng)
        _write_dat(path, stage, S)
        paths.append(path)
    return paths


@pytest.mark.slow
def test_reader_and_cli_on_a_synthetic_recording(tmp_path, rng):
    paths = _synthetic_recordings(tmp_path, rng)
    rec = read_ilemt(paths[0])
    assert rec.n_points == 83 and rec.home[0] and rec.home[-1] and rec.home.sum() == 3
    out = tmp_path / "tracker.json"
    runner = CliRunner()
    result = runner.invoke(cli, ["tracker", "calibrate", *map(str, paths), "-o", str(out), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["calibration"]["residue_rms_percent"] < 0.01  # the noise: 3e-5
    assert report["calibration"]["pose"]["position_rms_mm"] < 0.05
    tracker = load_tracker(out)
    assert tracker.calibration["model"] == "per-coil offsets" and "fixtures" in tracker.calibration
    result = runner.invoke(cli, ["tracker", "check", str(out), str(paths[1])])
    assert result.exit_code == 0, result.output
    assert "pose error" in result.output and "range" in result.output
    # refuses to overwrite without --force, and never a recording
    result = runner.invoke(cli, ["tracker", "calibrate", str(paths[0]), "-o", str(out)])
    assert result.exit_code != 0 and "exists" in result.output
    result = runner.invoke(cli, ["tracker", "calibrate", str(paths[0]), "-o", str(paths[0]), "--force"])
    assert result.exit_code != 0 and "never overwritten" in result.output


def test_reader_errors(tmp_path):
    bad = tmp_path / "soYoutZup_seYoutZup_md.dat"
    bad.write_text("0\t0\t0\t0\t0\t0\t+1+2i\n")
    with pytest.raises(CsvError, match="line 1: 7 fields"):
        read_ilemt(bad)
    bad.write_text("\t".join(["0"] * 6 + ["+1+2j"] * 18) + "\n")
    with pytest.raises(CsvError, match="not a complex value"):
        read_ilemt(bad)
    other = tmp_path / "recording.dat"
    other.write_text("")
    with pytest.raises(InputError, match="so<fixture>_se<fixture>"):
        read_ilemt(other)
    result = CliRunner().invoke(cli, ["tracker", "check", str(bad), str(bad)])
    assert result.exit_code == 1 and "Traceback" not in result.output


def test_rig_csv_round_trip_and_cli(tmp_path, rng):
    from ivc.collect.rig_csv import read_rig_csv, write_rig_csv
    from ivc.sim.stage import stage_pattern

    truth = Tracker(np.eye(3) + 0.03 * rng.standard_normal((3, 3)), np.eye(3) + 0.03 * rng.standard_normal((3, 3)))
    fixtures = Fixtures(stage=rigid_transform(t=np.array([0.0, 0.26, 0.0])))
    J_so, J_st = stage_pattern(rz_deg=(-90.0, 0.0, 90.0))
    S = stage_recording(truth, fixtures, J_so, J_st, noise_relative=1e-5, rng=rng)
    path = tmp_path / "rig.csv"
    write_rig_csv(path, S, J_st)
    S2, J_so2, J_st2 = read_rig_csv(path)
    np.testing.assert_array_equal(S2, S)
    np.testing.assert_allclose(J_st2, J_st, atol=1e-15)
    np.testing.assert_array_equal(J_so2, J_so)
    out = tmp_path / "t.json"
    result = CliRunner().invoke(cli, ["tracker", "calibrate", str(path), "-o", str(out), "--one-centre", "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["calibration"]["residue_rms_percent"] < 0.01
    # millimetre columns and a source rotation
    text = path.read_text().splitlines()
    text[0] = text[0].replace("x,y,z", "x_mm,y_mm,z_mm")
    mm = tmp_path / "mm.csv"
    mm.write_text("\n".join([text[0]] + [",".join([str(1e3 * float(v)) for v in line.split(",")[:3]]
                                                   + line.split(",")[3:]) for line in text[1:]]) + "\n")
    np.testing.assert_allclose(read_rig_csv(mm)[2], J_st, atol=1e-12)
    write_rig_csv(path, S, J_st, J_so)
    assert np.array_equal(read_rig_csv(path)[1], J_so)


def test_rig_csv_errors(tmp_path):
    from ivc.collect.rig_csv import read_rig_csv

    path = tmp_path / "rig.csv"
    path.write_text("x,y,z,qw,qx,qy,qz\n0,0,0,1,0,0,0\n")
    with pytest.raises(CsvError, match="missing columns s00"):
        read_rig_csv(path)
    columns = "x,y,z,qw,qx,qy,qz," + ",".join(f"s{i}{j}" for i in range(3) for j in range(3))
    path.write_text(columns + "\n" + ",".join(["0"] * 3 + ["1", "0", "0", "0"] + ["1"] * 9) + "\n"
                    + ",".join(["0"] * 3 + ["1", "0", "0"] + ["1"] * 9) + "\n")
    with pytest.raises(CsvError, match="lines 3"):
        read_rig_csv(path)
    path.write_text(columns + "\n" + ",".join(["0"] * 3 + ["2", "0", "0", "0"] + ["1"] * 9) + "\n")
    with pytest.raises(CsvError, match="line 2: qw,qx,qy,qz is not a unit quaternion"):
        read_rig_csv(path)
    path.write_text("a,b\n1,2\n")
    with pytest.raises(CsvError, match="x,y,z"):
        read_rig_csv(path)


def test_recording_as_a_session_step(tmp_path, rng):
    from ivc import session as session_io
    from ivc.collect.tracker_units import apply_tracker
    from ivc.pose.calibrate import chain
    from ivc.pose.tracker import tracker_pose
    from ivc.session import Session

    paths = _synthetic_recordings(tmp_path, rng)
    recs = [read_ilemt(p) for p in paths]
    result = calibrate(*stack(recs)[:3], offsets=False, output_correction=False)
    step, truth = recs[1].to_step(result.fixtures)
    assert step.signal.shape == (83, 1, 3, 3) and truth.position.shape == (83, 1, 3)
    data = Session(hemisphere="+y", steps={"check": step}, truth={"check": truth})
    path = tmp_path / "ilemt.h5"
    session_io.write(data, path)
    back = session_io.read(path)
    np.testing.assert_array_equal(back.steps["check"].signal, step.signal)
    np.testing.assert_array_equal(back.steps["check"].attrs["stage_poses"], recs[1].stage_compensated)
    # in ideal units, the closed form gives the chain's poses (to the synthetic noise and the coil offsets)
    home = truth.position[0, 0]
    axis = int(np.argmax(np.abs(home)))
    hemisphere = ("+" if home[axis] > 0 else "-") + "xyz"[axis]
    ideal = apply_tracker(step, result.tracker, hemisphere, "fit")
    P = chain(result.fixtures, recs[1].J_so, recs[1].J_st)
    solved = tracker_pose(step.signal[:, 0], result.tracker, P[:, :3, 3])
    closed = np.linalg.norm(ideal.poses(hemisphere)[0][:, 0] - P[:, :3, 3], axis=1)
    assert np.median(closed) < 3e-3 and np.median(np.linalg.norm(solved.position - P[:, :3, 3], axis=1)) < 3e-3
    assert recs[0].to_step()[1] is None


def test_reader_applies_no_sign_fix_unless_told(tmp_path, rng):
    paths = _synthetic_recordings(tmp_path, rng)
    plain = read_ilemt(paths[0])
    assert np.all(plain.source_signs == 1) and np.all(plain.sensor_signs == 1)
    told = read_ilemt(paths[0], sign_fixes=[parse_sign_fix("seYoutZup_md=-1,1,-1/1,-1,1")])
    np.testing.assert_array_equal(told.source_signs, [-1, 1, -1])
    np.testing.assert_array_equal(told.sensor_signs, [1, -1, 1])
    # coupling C(source, sensor): source rows and sensor columns negated
    np.testing.assert_array_equal(told.coupling, plain.coupling * np.array([-1, 1, -1])[:, None] * [1, -1, 1])
    assert np.all(read_ilemt(paths[1], sign_fixes=[parse_sign_fix("seYoutZup_md=-1,1,-1")]).source_signs == 1)
    # the folder's options file is the data set telling
    (tmp_path / OPTIONS_FILE).write_text('[[sign_fix]]\nfiles = "seZinYup_md\\\\.dat$"\nsource = [-1, -1, 1]\n')
    np.testing.assert_array_equal(read_ilemt(paths[1]).source_signs, [-1, -1, 1])
    assert np.all(read_ilemt(paths[0]).source_signs == 1)
    assert np.all(read_ilemt(paths[1], sign_fixes=()).source_signs == 1)
    for bad in ("seYoutZup=-1,1", "=1,1,1", "x=1,2,1", "(=1,1,1", "a=1,1,1/1,1,1/1,1,1"):
        with pytest.raises(InputError, match="sign fix"):
            parse_sign_fix(bad)
    (tmp_path / OPTIONS_FILE).write_text("[[sign_fix]]\nsource = [1, 1, 1]\n")
    with pytest.raises(InputError, match="files ="):
        read_ilemt(paths[1])


@pytest.mark.slow
def test_cli_warns_of_a_flipped_coil_and_takes_a_sign_fix(tmp_path, rng):
    paths = _synthetic_recordings(tmp_path, rng)
    lines = paths[2].read_text().splitlines()
    flipped = []
    for line in lines:  # negate source coil x (values k = 0, 3, 6 of each carrier: C[0, sensor])
        fields = line.split("\t")
        for k in (0, 3, 6, 9, 12, 15):
            value = fields[6 + k]
            fields[6 + k] = ("-" if value[0] == "+" else "+") + value[1:].replace("+", "#").replace("-", "+").replace(
                "#", "-")
        flipped.append("\t".join(fields))
    paths[2].write_text("\n".join(flipped) + "\n")
    out = tmp_path / "t.json"
    runner = CliRunner()
    result = runner.invoke(cli, ["tracker", "calibrate", *map(str, paths), "-o", str(out), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert [f["recording"] for f in report["sign_findings"]] == [paths[2].name]
    assert report["sign_findings"][0]["source_signs"] == [-1, 1, 1]
    fix = f"{paths[2].stem}=-1,1,1"
    result = runner.invoke(cli, ["tracker", "calibrate", *map(str, paths), "-o", str(out), "--force", "--json",
                                 "--sign-fix", fix])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["sign_findings"] == [] and report["calibration"]["residue_rms_percent"] < 0.01
    assert load_tracker(out).calibration["sign_fixes"] == [[paths[2].stem, [-1.0, 1.0, 1.0]]]
