"""Zero, denormal, huge and non-finite signal matrices marked valid (issue 41, items 8 and 9): every compiled solve
flags or drops the sample, never raises (numba's ``SystemError ... returned a result with an exception set``,
or ``ZeroDivisionError`` in a kernel run interpreted), and the other samples come out exactly as without it."""

import re

import numpy as np
import pytest

from ivc import compiled, dipole, rotations
from ivc.correct import INVALID_INPUT, NOT_CONVERGED, Corrector
from ivc.correct import kernels as _kernels
from ivc.correct.evaluate import check_errors, evaluate
from ivc.session import Session, Step, Truth
from tests.helpers import distorted

#: what a dropout, a unit or scaling slip, or a broken driver puts into a signal matrix
EDGES = [0.0, 1e300, 1e-300, -1e-300, np.inf, np.nan]
IDS = ["zero", "huge", "denormal", "negative-denormal", "inf", "nan"]


def poisoned(S, index, value):
    """A copy of S (..., 3, 3) with every entry of the sample at ``index`` set to ``value``."""
    S = np.array(S, float)
    S[index] = value
    return S


def test_usable_signals_tells_the_edges_from_real_signals(rng):
    r, T, S = distorted(rng, 50)
    assert dipole.usable_signals(S).all()
    far = dipole.signal(np.array([[2000.0, 0, 0]]), np.eye(3)[None], np.zeros((1, 3, 3)))  # 2 km: still a source
    near = dipole.signal(np.array([[0.001, 0, 0]]), np.eye(3)[None], np.zeros((1, 3, 3)))
    assert dipole.usable_signals(far).all() and dipole.usable_signals(near).all()
    edges = np.stack([np.full((3, 3), v) for v in EDGES])
    assert not dipole.usable_signals(edges).any()
    assert dipole.usable_signals(S.reshape(5, 10, 3, 3)).shape == (5, 10)


@pytest.mark.parametrize("value", EDGES, ids=IDS)
def test_a_step_drops_an_unusable_signal_from_its_valid_mask(value, rng):
    _, _, S = distorted(rng, 12)
    step = Step(np.arange(4) / 240, signal=poisoned(S.reshape(4, 3, 3, 3), (2, 1), value))
    expected = np.ones((4, 3), bool)
    expected[2, 1] = False
    np.testing.assert_array_equal(step.valid_mask, expected)


@pytest.mark.parametrize("value", EDGES, ids=IDS)
@pytest.mark.parametrize("interpreted", [False, True], ids=["compiled", "interpreted"])
def test_correct_batch_and_stream_flag_the_sample_and_keep_the_others(value, interpreted, exact_table, rng,
                                                                      monkeypatch):
    r, T, S = distorted(rng, 8)
    if interpreted:  # what a few frames get before the kernels are compiled (the live loop's first frames)
        monkeypatch.setattr(compiled, "SMALL", 64)
        monkeypatch.setattr(compiled, "is_ready", lambda kernel: False)
    clean = Corrector(exact_table).batch(S)
    bad = poisoned(S, 3, value)
    for out in (Corrector(exact_table).batch(bad), Corrector(exact_table).update(bad)):
        assert out.flags[3] == INVALID_INPUT and np.all(np.isnan(out.position[3]))
        keep = np.arange(8) != 3
        np.testing.assert_array_equal(out.flags[keep], clean.flags[keep])
        np.testing.assert_allclose(out.position[keep], clean.position[keep], atol=1e-12)


def _losing_sample(monkeypatch, lost=1):
    """Make the correction kernels end sample ``lost`` of every call "converged" at a NaN pose: a solve that ran off
    (no input is known to do it; this is the net under one that would)."""
    choose = compiled.choose

    def losing(kernel, samples, *args):
        run = choose(kernel, samples, *args)
        if kernel not in (_kernels.correct_serial, _kernels.correct_kernel):
            return run

        def lose(*a):
            run(*a)
            r, T, q, converged = a[6][:4]  # the kernels' Output bundle: r, T, q, converged, ...
            r[lost], T[lost], q[lost], converged[lost] = np.nan, np.nan, np.nan, True

        return lose

    monkeypatch.setattr(compiled, "choose", losing)


def test_a_sample_the_solve_leaves_without_a_pose_is_flagged_and_written(exact_table, table_file, tmp_path, rng,
                                                                         monkeypatch):
    from ivc import session as session_io

    r, T, S = distorted(rng, 6)
    _losing_sample(monkeypatch)
    out = Corrector(exact_table).batch(S)
    assert out.flags[1] & NOT_CONVERGED and np.all(out.flags[[0, 2, 3, 4, 5]] == 0)
    session_io.write(Session("+x", {"check": Step(np.arange(6) / 240, signal=S[:, None])}), tmp_path / "s.h5")
    result = _correct([table_file, tmp_path / "s.h5", "-o", tmp_path / "out.h5"])
    assert result.exit_code == 0, result.output
    written = session_io.read(tmp_path / "out.h5").steps["check"]
    assert written.valid[:, 0].tolist() == [True, False, True, True, True, True]
    import h5py

    with h5py.File(tmp_path / "out.h5") as h5:
        assert h5["steps/check/flags"][1, 0] & NOT_CONVERGED


@pytest.mark.parametrize("value", EDGES, ids=IDS)
def test_evaluate_flags_the_sample(value, exact_table, rng):
    r, T, S = distorted(rng, 40)
    q = rotations.from_matrix(T)[:, None]
    check = Session("+x", {"check": Step(np.arange(40) / 240, signal=poisoned(S, 7, value)[:, None])},
                    {"check": Truth(r[:, None], q)})
    errors = check_errors(exact_table, check)
    assert errors.flags[7, 0] == INVALID_INPUT and not errors.ok[7, 0] and not errors.valid[7, 0]
    assert errors.ok.sum() == 39
    assert evaluate(exact_table, check)["ivc"]["position_mm"]["p50"] < 1e-6  # the other 39 exact


# ---- the fit's solves: the cube solve, the sweep's mapping, the rigid-wand refinement and joint solve, the fit,
# the report

#: (frame, sensor) of the poisoned sweep samples: one on sensor 0 (solved in the cube), one on another sensor
SWEEP_SAMPLES = ((5, 0), (6, 3))


@pytest.fixture(scope="module")
def fitted(small_session):
    """The small session's fixtures and a table fitted without refinement (the refinement is tested alone)."""
    from ivc.fixtures.mapping import FixtureModel
    from ivc.lut import FitOptions, fit_lut

    _, session = small_session
    return session, FixtureModel.from_session(session), fit_lut(session, FitOptions(min_support=5, refine=False))


def poisoned_session(session, value, steps=("wand_sweep",), frames=300):
    """The session's first ``frames`` sweep frames, with SWEEP_SAMPLES of the sweep (and frame 2's last sensor in any
    other step in ``steps``) set to ``value``, still marked valid."""
    part = session.select_frames("wand_sweep", slice(0, frames))
    out = Session(part.hemisphere, dict(part.steps), part.truth, part.attrs)
    for name in steps:
        step = out.steps[name]
        signal = np.array(step.signal, float)
        for frame, sensor in SWEEP_SAMPLES if name == "wand_sweep" else ((2, step.n_sensors - 1),):
            signal[frame, sensor] = value
        out.steps[name] = Step(step.time, signal, step.position, step.quaternion, step.valid, step.sample_rate_hz,
                               step.sensor_ids, step.description, step.attrs)
    return out


@pytest.mark.parametrize("value", EDGES, ids=IDS)
def test_the_cube_solve_returns_the_frame_unsolved(value, fitted):
    from ivc.fixtures.cube_pose import solve_in_cube

    session, model, _ = fitted
    S = session.steps["wand_sweep"].signal[:40, 0]
    centre = model.placement.positions.mean(axis=0)
    clean = solve_in_cube(S, model.interpolant, centre)
    out = solve_in_cube(poisoned(S, 5, value), model.interpolant, centre)
    assert not out.converged[5] and np.all(np.isnan(out.position[5])) and np.isnan(out.residual[5])
    keep = np.arange(40) != 5
    np.testing.assert_array_equal(out.position[keep], clean.position[keep])
    np.testing.assert_array_equal(out.converged[keep], clean.converged[keep])


@pytest.mark.parametrize("value", EDGES, ids=IDS)
def test_the_sweep_mapping_drops_the_samples_and_counts_them(value, fitted):
    from ivc.fixtures.mapping import map_sweep

    session, model, _ = fitted
    clean = map_sweep(session.select_frames("wand_sweep", slice(0, 300)), model)
    out = map_sweep(poisoned_session(session, value), model)
    assert not out.keep[5].any() and not out.keep[6, 3]
    expected = clean.keep.copy()
    expected[5], expected[6, 3] = False, False
    np.testing.assert_array_equal(out.keep, expected)
    assert session.steps["wand_sweep"].valid_mask[5, 0] and session.steps["wand_sweep"].valid_mask[6, 3]
    assert out.dropped["invalid sample"] == clean.dropped["invalid sample"] + 2  # the rest of frame 5: sensor 0's
    assert sum(out.dropped.values()) == sum(clean.dropped.values()) + int(clean.keep[5].sum()) + int(clean.keep[6, 3])


@pytest.mark.parametrize("value", EDGES, ids=IDS)
def test_the_rigid_wand_solves_skip_the_samples(value, fitted):
    from ivc.fixtures.mapping import map_sweep
    from ivc.lut.joint import solve_wand_table
    from ivc.lut.refine import solve_rigid

    session, model, table = fitted
    part = session.select_frames("wand_sweep", slice(0, 100))
    mapping = map_sweep(part, model)
    sweep = part.steps["wand_sweep"]
    start_r, start_T = mapping.positions[:, 0], mapping.rotations[:, 0]
    bad = poisoned(sweep.signal, SWEEP_SAMPLES[0], value)
    bad[SWEEP_SAMPLES[1]] = value
    others = ~np.isin(np.arange(100), [5, 6])
    for compiled_solve in (True, False):
        args = (model.wand, model.interpolant.value_and_jacobian, table.field(), start_r, start_T)
        r0, T0, ok0 = solve_rigid(sweep.signal, sweep.valid_mask, *args, compiled=compiled_solve)
        r, T, ok = solve_rigid(bad, sweep.valid_mask, *args, compiled=compiled_solve)
        np.testing.assert_array_equal(ok[others], ok0[others])
        np.testing.assert_array_equal(r[others], r0[others])
    use = np.ones((100, sweep.n_sensors), bool)
    clean = solve_wand_table(sweep.signal, use, model.wand, table.field(), start_r, start_T)
    out = solve_wand_table(bad, use, model.wand, table.field(), start_r, start_T)
    assert not out.used[5, 0] and not out.used[6, 3]
    np.testing.assert_array_equal(out.position[others], clean.position[others])


@pytest.mark.parametrize("value", EDGES, ids=IDS)
def test_the_report_counts_the_samples_dropped_and_flags_the_check_sample(value, fitted):
    from ivc.report.compute import gather

    session, _, table = fitted
    clean = gather(session.select_frames("wand_sweep", slice(0, 300)), table)
    data = gather(poisoned_session(session, value, ("wand_sweep", "check", "cube_survey", "cube_calibration")), table)
    dropped, before = data.sweep.mapping.dropped, clean.sweep.mapping.dropped
    assert dropped["invalid sample"] == before["invalid sample"] + 2
    assert data.check.errors.flags[2, 0] == INVALID_INPUT and not data.check.errors.valid[2, 0]


@pytest.mark.parametrize("value", EDGES, ids=IDS)
def test_a_fit_drops_the_unusable_samples_and_counts_them(value, fitted):
    """A fit (with a refinement: the rigid-wand solve) of the session with ``value`` in each static step and in the
    sweep: the fit's report counts the sweep's among the invalid samples."""
    from ivc.fixtures.mapping import map_sweep
    from ivc.lut import FitOptions, fit_lut

    session, model, _ = fitted
    steps = ("cube_calibration", "cube_survey", "wand_calibration", "wand_sweep")
    bad = poisoned_session(session, value, steps, frames=session.steps["wand_sweep"].n_frames)
    table = fit_lut(bad, FitOptions(min_support=5, max_refinements=1))
    clean = map_sweep(session, model).dropped["invalid sample"]
    assert table.fit["samples"]["dropped"]["invalid sample"] == clean + 2
    assert table.fit["refinement"] and np.isfinite(table.fit["cv_rms_mm"]) and table.valid.any()


# ---- `ivc correct` writes a flagged sample in every output format (item 9)

PLUS_TEMPLATE = """ObjectType = Image
NDims = 3
DimSize = 0 0 {frames}
ElementType = MET_UCHAR
{body}ElementDataFile = LOCAL
"""


def _correct(args):
    from click.testing import CliRunner

    from ivc.cli import cli

    return CliRunner().invoke(cli, ["correct", *map(str, args)])


@pytest.fixture
def table_file(exact_table, tmp_path):
    from ivc.lut import write as write_lut

    path = tmp_path / "lut.h5"
    write_lut(exact_table, path)
    return path


@pytest.mark.parametrize("value", EDGES, ids=IDS)
def test_correct_writes_the_flagged_sample_into_a_session_and_a_csv(value, table_file, tmp_path, rng):
    from ivc import session as session_io
    from ivc.collect.replay import write_csv

    r, T, S = distorted(rng, 30)
    S = poisoned(S, 4, value)
    S[9] = np.diag([1e4, 1e-8, 1e-8])  # usable, but no pose explains it
    step = Step(np.arange(30) / 240, signal=S[:, None])
    if not np.isfinite(value):  # not a file ivc reads: the readers refuse it, naming the sample (no traceback)
        with pytest.raises(session_io.SessionError, match="NaN or inf"):
            session_io.write(Session("+x", {"check": step}), tmp_path / "s.h5")
        return
    session_io.write(Session("+x", {"check": step}), tmp_path / "s.h5")
    result = _correct([table_file, tmp_path / "s.h5", "-o", tmp_path / "out.h5"])
    assert result.exit_code == 0, result.output
    import h5py

    with h5py.File(tmp_path / "out.h5") as h5:
        flags = h5["steps/check/flags"][()][:, 0]
    out = session_io.read(tmp_path / "out.h5").steps["check"]
    assert flags[4] == INVALID_INPUT and not out.valid[4, 0] and np.all(np.isnan(out.position[4]))
    assert flags[9] != 0 and (out.valid[9, 0] == np.all(np.isfinite(out.position[9])))
    assert np.sum(flags == 0) >= 28 - 1 and out.valid.sum() >= 28

    write_csv(step, tmp_path / "in.csv")
    result = _correct([table_file, tmp_path / "in.csv", "-o", tmp_path / "out.csv"])
    assert result.exit_code == 0, result.output
    lines = (tmp_path / "out.csv").read_text().splitlines()
    header = lines[0].split(",")
    rows = [dict(zip(header, line.split(","), strict=True)) for line in lines[1:]]
    assert len(rows) == 30 and int(rows[4]["flags"]) == INVALID_INPUT and rows[4]["valid"] == "0"
    assert [int(row["flags"]) for row in rows] == flags.tolist()


@pytest.mark.parametrize("translation", ["0 0 0", "1e-300 0 0", "-1e-300 0 -1e-300"], ids=["origin", "denormal",
                                                                                           "negative-denormal"])
def test_correct_writes_an_unsolvable_pose_into_plus_and_csv(translation, table_file, tmp_path):
    from ivc.collect import read_plus

    frames = [(f"1 0 0 {300 + k} 0 1 0 {k} 0 0 1 0 0 0 0 1" if k != 2 else
               "1 0 0 {} 0 1 0 {} 0 0 1 {} 0 0 0 1".format(*translation.split())) for k in range(5)]
    body = "".join(f"Seq_Frame{k:04d}_ToolToTrackerTransform = {m}\n"
                   f"Seq_Frame{k:04d}_ToolToTrackerTransformStatus = OK\n"
                   f"Seq_Frame{k:04d}_Timestamp = {1 + k / 240}\n" for k, m in enumerate(frames))
    path = tmp_path / "in.igs.mha"
    path.write_text(PLUS_TEMPLATE.format(frames=5, body=body))
    for out in (tmp_path / "out.igs.mha", tmp_path / "out.csv"):
        result = _correct([table_file, path, "-o", out])
        assert result.exit_code == 0, result.output
    text = (tmp_path / "out.igs.mha").read_text("latin-1")
    flags = [int(v) for v in re.findall(r"ToolToTrackerIvcFlags = (\d+)", text)]
    assert len(flags) == 5 and flags[2] != 0
    assert "Seq_Frame0002_ToolToTrackerIvcTransformStatus = INVALID" in text
    assert read_plus(tmp_path / "out.igs.mha").step.n_frames == 5
    lines = (tmp_path / "out.csv").read_text().splitlines()
    assert len(lines) == 6 and int(lines[3].split(",")[lines[0].split(",").index("flags")]) == flags[2]


@pytest.mark.parametrize("value", EDGES, ids=IDS)
def test_the_live_loop_names_an_unusable_signal_matrix(value):
    from ivc.live.igtl import Frame
    from ivc.live.loop import unusable_frames

    frames = [Frame("NDARRAY", "coil", 0.0, np.full((3, 3), value)), Frame("NDARRAY", "coil", 0.0, np.eye(3))]
    problems = unusable_frames(frames, 1e-3)
    assert set(problems) == {0} and problems[0]
