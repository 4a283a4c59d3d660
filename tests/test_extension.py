"""Extension sweeps in the session format, the simulator, `ivc collect` and `ivc fit` (issue: whole-volume maps)."""

import numpy as np
import pytest
from click.testing import CliRunner

from ivc import lut
from ivc import session as session_io
from ivc.cli.main import cli
from ivc.collect.checks import reach_warning
from ivc.session import STEPS, SessionError, extension_step, extension_steps, is_extension_step
from ivc.sim import Simulator, load_scene, rig
from ivc.sim.scene import scene_from_dict

PLATE = {"shape": "plate", "size": [1.0, 1.0], "position": [0.55, 0, -0.4], "material": "aluminium",
         "resolution_mm": 80}
FRAMES = {"cube_calibration": 1000, "cube_survey": 200, "wand_calibration": 200, "wand_sweep": 3000, "check": 200}


def box_scene(sweeps: int = 2):
    scene = scene_from_dict({"conductor": [PLATE], "cube": {"center": [0.55, 0, 0]},
                             "volume": {"center": [0.55, 0, 0], "size": [0.6, 0.5, 0.4]},
                             "extension": {"sweeps": sweeps, "frames": 1500}})
    scene.tabulate = False
    return scene


def test_step_names():
    assert extension_step(3) == "extension_sweep_3"
    assert is_extension_step("extension_sweep_12")
    for name in ("extension_sweep_0", "extension_sweep_01", "extension_sweep_100", "extension_sweep_x", "wand_sweep"):
        assert not is_extension_step(name)
    assert extension_steps(["check", "extension_sweep_10", "extension_sweep_2"]) == ["extension_sweep_2",
                                                                                    "extension_sweep_10"]
    with pytest.raises(SessionError):
        extension_step(0)


def test_simulated_extension_sweeps_round_trip_and_stay_in_the_box(tmp_path):
    sim = Simulator(box_scene(), seed=1)
    assert sim.steps == [*STEPS[:4], "extension_sweep_1", "extension_sweep_2", "check"]
    session = sim.protocol(FRAMES)
    path = tmp_path / "s.h5"
    session_io.write(session, path)
    back = session_io.read(path)
    assert list(back.steps) == sim.steps
    for name in ("extension_sweep_1", "extension_sweep_2"):
        np.testing.assert_array_equal(back.steps[name].signal, session.steps[name].signal)
        truth = back.truth[name].position
        volume = sim.scene.volume
        beyond = max(-rig.PASS_MARGIN, 0.0) + 0.005  # the outermost passes run just beyond the faces
        assert np.all(truth >= volume.lower - beyond) and np.all(truth <= volume.upper + beyond)
        # held at its far end: the hand (last sensor) further from the cube than the tip, on the whole
        distance = np.linalg.norm(truth - sim.scene.cube.center, axis=-1)
        assert np.median(distance[:, -1]) > np.median(distance[:, 0])
    # a step simulated alone equals the same step within the protocol
    alone, _ = sim.step("extension_sweep_2", 1500)
    np.testing.assert_array_equal(alone.signal, session.steps["extension_sweep_2"].signal)
    # the wand of an extension sweep must be the calibrated one
    session.steps["extension_sweep_1"] = session.steps["extension_sweep_1"].select(slice(None))
    session.steps["extension_sweep_1"].signal = session.steps["extension_sweep_1"].signal[:, :4]
    session.steps["extension_sweep_1"].position = session.steps["extension_sweep_1"].position[:, :4]
    session.steps["extension_sweep_1"].quaternion = session.steps["extension_sweep_1"].quaternion[:, :4]
    session.steps["extension_sweep_1"].valid = session.steps["extension_sweep_1"].valid[:, :4]
    session.steps["extension_sweep_1"].sensor_ids = None
    session.truth.pop("extension_sweep_1")
    with pytest.raises(SessionError, match="extension_sweep_1: 4 sensors"):
        session.validate()


def test_unknown_step_names_are_refused():
    sim = Simulator(box_scene(), seed=1)
    session = sim.protocol(FRAMES, steps=["cube_calibration"])
    session.steps["extension_sweep_0"] = session.steps["cube_calibration"]
    with pytest.raises(SessionError, match="unknown step"):
        session.validate()
    with pytest.raises(Exception, match="no working volume"):
        Simulator(load_scene("mild"), 0).step("extension_sweep_1", 10)


def test_old_single_sweep_sessions_fit_exactly_as_before():
    """A scene's extension sweeps change nothing of its five steps, and a session without them is
    fitted by the single-sweep path, bit for bit."""
    with_extension = Simulator(box_scene(2), seed=4).protocol(FRAMES)
    without = Simulator(box_scene(0), seed=4).protocol(FRAMES)
    assert set(without.steps) == set(STEPS)
    for name in STEPS:
        np.testing.assert_array_equal(with_extension.steps[name].signal, without.steps[name].signal)
    single = with_extension.select_frames("wand_sweep", slice(None))
    for name in extension_steps(list(single.steps)):
        del single.steps[name], single.truth[name]
    a, b = lut.fit_lut(single), lut.fit_lut(without)
    np.testing.assert_array_equal(a.values, b.values)
    np.testing.assert_array_equal(a.valid, b.valid)
    assert "rounds" not in a.fit and a.fit["method"] == "harmonic"


def test_reach_warning():
    sim = Simulator(box_scene(1), seed=2)
    session = sim.protocol(FRAMES, steps=STEPS[:4])
    step, _ = sim.step("extension_sweep_1", 1500)
    assert reach_warning("extension_sweep_1", step, session) is None
    far = step.select(slice(None))
    far.position = far.position + np.array([2.0, 0, 0])
    message = reach_warning("extension_sweep_1", far, session)
    assert message and "never came near the region mapped from the cube" in message


def test_collect_records_an_extension_sweep(tmp_path):
    scene = tmp_path / "box.toml"
    scene.write_text('[cube]\ncenter = [0.55, 0, 0]\n[volume]\ncenter = [0.55, 0, 0]\nsize = [0.6, 0.5, 0.4]\n'
                     'tabulate_spacing_mm = 20\n[extension]\nsweeps = 1\nframes = 300\n')
    out = tmp_path / "s.h5"
    runner = CliRunner()
    result = runner.invoke(cli, ["collect", "extension_sweep_1", "--source", f"sim:{scene}", "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert "extension_sweep_1" in session_io.read(out).steps
    result = runner.invoke(cli, ["collect", "extension_sweep_0", "--source", f"sim:{scene}", "-o", str(out)])
    assert result.exit_code != 0 and "extension_sweep_N" in result.output


@pytest.mark.slow
def test_joint_fit_grows_the_map_and_reports_it(tmp_path):
    from ivc.correct.evaluate import evaluate
    from ivc.lut.joint import JointOptions, fit_joint, mapped_litres, to_table
    from ivc.report import build_report

    scene = box_scene(2)
    scene.extension.frames = 3000
    session = Simulator(scene, seed=5).protocol(FRAMES)
    # sources 0.1 m apart, not the default 0.07 m: the same mapped volume and checks at half the fit's cost
    # (the cockpit benchmark runs the defaults)
    joint = fit_joint(session, JointOptions(max_iterations=2, max_extension_frames=1500, source_spacing=0.1,
                                             max_samples=8000))
    rounds = joint.report["rounds"]
    assert [r["iteration"] for r in rounds] == [0, 1, 2]
    assert joint.report["samples_used"] <= 8000 < rounds[-1]["samples"]  # the cap holds: the sweeps found more
    assert joint.report["max_samples"] == 8000
    assert rounds[-1]["mapped_litres"] > 1.2 * rounds[0]["mapped_litres"]
    assert all(n > 0 for n in rounds[-1]["frames_solved"].values())
    assert joint.report["never_touched_mapped_region"] == []
    assert len(joint.report["error_by_distance"]) == 5
    table = to_table(joint, session.hemisphere)
    assert mapped_litres(table.grid, table.valid) == pytest.approx(joint.report["mapped_litres"])
    result = evaluate(table, session)
    assert result["ivc"]["position_mm"]["p50"] < 0.2 * result["dipole"]["position_mm"]["p50"]
    report = build_report(session, table, tmp_path / "report")
    assert report.numbers["volume"]["rounds"] == rounds
    page = (tmp_path / "report" / "report.html").read_text()
    assert "Whole working volume" in page
    # the session declares the scene's box: the report gives the share of it the table maps
    box = report.numbers["box"]
    assert box["box_litres"] == pytest.approx(120.0) and 0.0 < box["fraction"] <= 1.0
    assert box["mapped_litres"] <= joint.report["mapped_litres"] + 1.0  # the 1 cm lattice: within a litre
    assert box["mapped_litres"] == pytest.approx(box["fraction"] * 120.0, abs=0.01)
    assert "Declared working volume" in page
    # the region each sweep maps: the cube sweep as the report solves it, each extension sweep re-solved against
    # the final map (the fit's last round solved it against the map before, so about as many frames are kept)
    regions = report.numbers["sweep_regions"]
    assert [r["name"] for r in regions] == ["wand_sweep", "extension_sweep_1", "extension_sweep_2"]
    assert regions[0]["samples"] == report.numbers["sweep"]["samples"]["kept"]
    for region in regions[1:]:
        assert region["frames_kept"] >= 0.9 * rounds[-1]["frames_solved"][region["name"]]
        assert region["frames_solved"] == 1500 and region["stride"] == 2
    assert report.numbers["coverage"]["samples_kept"] == sum(r["samples"] for r in regions)
    for region in regions:
        assert 0 < region["mapped_litres_reached_by_it_alone"] <= region["mapped_litres_reached"]
        assert region["mapped_litres_reached"] <= joint.report["mapped_litres"] + 1e-6
        assert 0 < region["box_share_reached"] <= box["fraction"] + 0.02  # the lattice probes cells, not nodes
    # the mapped region needs samples: the sweeps' reached cells together hold most of it. The table is twice as
    # fine as the grid its support is counted on, so a mapped table cell need not hold a sample itself (its
    # support cell does): most of the mapped volume lies in cells with samples, nearly all of it at the support grid
    assert sum(r["mapped_litres_reached"] for r in regions) > 0.6 * joint.report["mapped_litres"]
    from ivc.table.grid import Grid

    assert joint.report["table_subdivision"] == 2 and joint.report["sample_selection"] == "even"
    assert joint.report["error_floor_mm"] == pytest.approx(1000 * JointOptions().error_floor)  # the joint's ε₀
    assert joint.report["support_spacing_m"] == pytest.approx(2 * joint.grid.spacing)
    coarse = Grid.around(joint.samples.positions, joint.report["support_spacing_m"])
    np.testing.assert_allclose(coarse.origin, joint.grid.origin)
    cells = np.floor((joint.samples.positions - coarse.origin) / coarse.spacing).astype(int)
    occupied = np.zeros(tuple(n - 1 for n in coarse.shape), dtype=bool)
    occupied[tuple(cells.T)] = True
    v = joint.valid[::2, ::2, ::2]
    mapped = (v[:-1, :-1, :-1] & v[1:, :-1, :-1] & v[:-1, 1:, :-1] & v[:-1, :-1, 1:] & v[1:, 1:, :-1]
              & v[1:, :-1, 1:] & v[:-1, 1:, 1:] & v[1:, 1:, 1:])
    assert v.shape == coarse.shape and (mapped & occupied).sum() > 0.9 * mapped.sum()
    assert "Region mapped by each sweep" in page and (tmp_path / "report" / "sweep_regions.png").exists()


@pytest.mark.slow
def test_the_joint_path_of_fit_lut_reports_typed_fields():
    scene = box_scene(1)
    scene.extension.frames = 1500
    session = Simulator(scene, seed=6).protocol(FRAMES)
    table = lut.fit_lut(session)
    report = table.report
    assert report.method == "equivalent sources, joint" and report.input == "signals"
    assert [r.iteration for r in report.rounds] == [r["iteration"] for r in table.fit["rounds"]]
    assert report.samples.anchor == table.fit["samples"]["anchor"] and report.sources == table.fit["sources"]
    assert report.model_text().startswith(f"{report.sources} dipoles, damping ")
    assert report.to_dict() == table.fit
