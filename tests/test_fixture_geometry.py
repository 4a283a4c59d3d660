"""The geometry file of a printed fixture (issue 40): its format, the declared frame it gives, and the build
check of calibrated sensors against it (swaps, wrong pockets, turned or loose sensors, another fixture)."""

import json

import numpy as np
import pytest

from ivc import rotations
from ivc.errors import FixtureError
from ivc.fixtures.build_check import Tolerances, check_build, check_cube, check_session, check_wand
from ivc.fixtures.cube import CubeCalibration
from ivc.fixtures.geometry import (
    FixtureGeometry,
    cube_layout,
    load_geometries,
    part_declared_pose,
    read_geometry,
    wand_layout,
)
from ivc.fixtures.wand import WandCalibration
from ivc.sim import Simulator, load_scene, rig
from ivc.sim.scene import scene_from_dict

CUBE = cube_layout("liberty-rx2")
WAND = wand_layout("aurora-6dof")


def _free_scene(**cube):
    scene = scene_from_dict({"cube": cube})
    scene.tabulate = False
    return scene


def _calibrate_cube(simulator, frames=200):
    return CubeCalibration.from_step(simulator.step("cube_calibration", frames)[0])


def _calibrate_wand(simulator, frames=200):
    return WandCalibration.from_step(simulator.step("wand_calibration", frames)[0])


def test_the_geometry_file_round_trips_and_refuses_what_is_malformed(tmp_path):
    path = CUBE.write(tmp_path / "cube.json")
    data = json.loads(path.read_text())
    assert data["format"] == "ivc-fixture-geometry" and data["version"] == 1 and data["kind"] == "cube"
    assert data["sensors"][4]["position_mm"][0] - data["sensors"][0]["position_mm"][0] == pytest.approx(50.8)
    back = read_geometry(path)
    for name in ("positions", "quaternions", "declared_position", "declared_quaternion", "extent"):
        assert np.allclose(getattr(back, name), getattr(CUBE, name), atol=1e-12), name
    assert back.options.__dict__ == pytest.approx(CUBE.options.__dict__, rel=1e-12)
    for name in ("length", "width", "height", "cable_diameter", "cable_height"):
        assert getattr(back.sensor, name) == pytest.approx(getattr(CUBE.sensor, name), rel=1e-12)
    assert np.allclose(back.sensor.origin, CUBE.sensor.origin) and back.sensor.axes == CUBE.sensor.axes
    assert back.sensor.flange == pytest.approx(CUBE.sensor.flange) and back.sensor.source == CUBE.sensor.source
    assert back.parameters["edge"] == pytest.approx(0.0508)

    def refused(change, match):
        broken = json.loads(path.read_text())
        change(broken)
        with pytest.raises(FixtureError, match=match):
            FixtureGeometry.from_dict(broken)

    refused(lambda d: d.update(version=2), "version 2")
    refused(lambda d: d.pop("format"), "not an ivc fixture geometry file")
    refused(lambda d: d["sensors"].pop(), "a cube holds 8 sensors")
    refused(lambda d: d["sensors"][3].update(quaternion=[1, 1, 0, 0]), "unit quaternion")
    refused(lambda d: d["sensors"][3].update(index=5), "indices")
    refused(lambda d: d["sensor"].update(shape="sphere"), "shape 'sphere'")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(FixtureError, match="not valid JSON"):
        read_geometry(tmp_path / "bad.json")
    with pytest.raises(FixtureError, match="second cube"):
        load_geometries([path, path])


def test_nominal_poses_in_the_declared_frame_are_the_calibrations_frame():
    positions, quaternions = CUBE.in_declared_frame()
    from ivc.fixtures.cube import CUBE_BITS

    assert np.allclose(positions, 0.0508 * CUBE_BITS, atol=1e-12)  # origin at sensor 0, x to 4, y to 2
    wand_positions, wand_quaternions = WAND.in_declared_frame()
    assert np.allclose(wand_positions[0], 0) and np.allclose(wand_quaternions[0], rotations.IDENTITY)
    assert np.allclose(np.linalg.norm(wand_positions, axis=1), 0.0254 * np.arange(8))


def test_the_declared_frame_from_the_geometry_file_equals_the_simulators_for_a_cube_placed_by_it():
    scene = _free_scene(placement_sigma_mm=0.0, placement_sigma_mrad=0.0, rotation_deg=[10, -20, 35])
    simulator = Simulator(scene, seed=4, cube_geometry=CUBE)
    simulator.cube = rig.build_fixture(CUBE, np.random.default_rng(0), position_sigma=0.0, angle_sigma=0.0)
    r0, T_I = simulator.true_cube_frame()
    position, quaternion = simulator.declared_cube_pose()
    assert np.allclose(position, r0, atol=1e-12)
    assert np.allclose(rotations.to_matrix(quaternion), T_I, atol=1e-12)
    part = simulator.cube_body_pose()  # where the part's corner mark is
    assert np.allclose(part_declared_pose(CUBE, *part)[0], r0, atol=1e-12)
    # a printed cube (the print's errors) placed without error: declared within the print's tolerance
    printed = Simulator(scene, seed=4, cube_geometry=CUBE)
    r0, T_I = printed.true_cube_frame()
    position, quaternion = printed.declared_cube_pose()
    assert 0 < np.linalg.norm(position - r0) < 0.5e-3
    assert rotations.angle_between_matrices(rotations.to_matrix(quaternion), T_I) < 0.005
    survey = printed.step("cube_survey", 5)[0]
    assert np.allclose(survey.attrs["declared_position"], position)


def test_collect_takes_the_declared_pose_of_a_printed_cube_from_its_part_frame(tmp_path):
    from click.testing import CliRunner

    from ivc import session as session_io
    from ivc.cli import cli

    (tmp_path / "free.toml").write_text('name = "free"\n')
    CUBE.write(tmp_path / "cube.json")
    q = rotations.canonical(rotations.from_rotvec([0.1, -0.2, 0.3]))
    result = CliRunner().invoke(cli, ["collect", "cube_survey", "-o", str(tmp_path / "s.h5"), "--source",
                                      f"sim:{tmp_path / 'free.toml'}", "--frames", "5", "--geometry",
                                      str(tmp_path / "cube.json"), "--declared-position", "0.4,0.01,-0.02",
                                      "--declared-quaternion", ",".join(map(str, q))])
    assert result.exit_code == 0, result.output
    attrs = session_io.read(tmp_path / "s.h5").steps["cube_survey"].attrs
    position, quaternion = CUBE.declared_pose([0.4, 0.01, -0.02], q)
    assert np.allclose(attrs["declared_position"], position) and np.allclose(attrs["declared_quaternion"], quaternion)
    assert not np.allclose(position, [0.4, 0.01, -0.02])  # the declared frame is not the corner mark
    half = CliRunner().invoke(cli, ["collect", "cube_survey", "-o", str(tmp_path / "t.h5"), "--source",
                                    f"sim:{tmp_path / 'free.toml'}", "--frames", "5", "--geometry",
                                    str(tmp_path / "cube.json"), "--declared-position", "0.4,0,0"])
    assert half.exit_code != 0 and "position and quaternion both" in half.output


def test_a_cube_built_wrong_is_reported_sensor_by_sensor_and_a_correct_one_passes_silently():
    simulator = Simulator(load_scene("default"), seed=2, cube_geometry=CUBE)
    correct = check_cube(_calibrate_cube(simulator), CUBE)
    assert correct.ok and correct.findings == [] and "matches its geometry file" in correct.render()
    simulator.cube = rig.build_fixture(CUBE, np.random.default_rng(5), swaps=((1, 6),),
                                       turns={3: [0.0, 0.0, np.pi / 2]}, lifts={4: [0.0, 0.0, 0.002]})
    report = check_cube(_calibrate_cube(simulator), CUBE)
    kinds = {(f.kind, f.sensors) for f in report.findings}
    assert kinds == {("swapped", (1, 6)), ("rotated", (3,)), ("not seated", (4,))}
    (turned,) = report.for_sensor(3)
    assert turned.angle_deg == pytest.approx(90, abs=1.5) and "about its z axis" in turned.message
    (lifted,) = report.for_sensor(4)
    assert lifted.offset_mm == pytest.approx(2.0, abs=0.4) and "up out of the pocket" in lifted.message
    assert [f.kind for f in report.for_sensor(6)] == ["swapped"]
    assert report.for_sensor(0) == [] and not report.ok


def test_a_sensor_in_another_pocket_a_wrong_fixture_and_a_wrong_count_are_named():
    rng = np.random.default_rng(8)
    fixture = rig.build_fixture(CUBE, rng)
    order = np.arange(8)
    order[[2, 5, 7]] = [5, 7, 2]  # sensor 2 in pocket 5's place, 5 in 7's, 7 in 2's
    report = check_build(fixture.body_positions[order], fixture.body_quaternions[order], CUBE)
    assert {(f.kind, f.sensors, f.pocket) for f in report.findings} == {
        ("other pocket", (2,), 5), ("other pocket", (5,), 7), ("other pocket", (7,), 2)}
    smaller = rig.build_fixture(cube_layout("liberty-rx2", 0.045), rng)
    wrong = check_build(smaller.body_positions, smaller.body_quaternions, CUBE)
    assert [f.kind for f in wrong.findings] == ["wrong fixture"] and "45.0 mm where the file has 50.8" in wrong.render()
    count = check_build(fixture.body_positions[:7], fixture.body_quaternions[:7], CUBE)
    assert count.findings[0].kind == "sensor count"
    assert check_wand(WandCalibration(fixture.body_positions, np.eye(3)[None].repeat(8, 0), np.ones(8)),
                      CUBE).findings[0].kind == "wrong fixture"


def test_the_check_is_a_pure_function_of_the_poses_whatever_their_frame():
    rng = np.random.default_rng(3)
    fixture = rig.build_fixture(WAND, rng, origin=None, swaps=((0, 3),), turns={5: [0.05, 0.0, 0.0]})
    q = rotations.random(1, rng)[0]
    R, t = rotations.to_matrix(q), np.array([0.3, -0.1, 0.2])
    moved = check_build(fixture.body_positions @ R.T + t, rotations.multiply(q, fixture.body_quaternions), WAND)
    here = check_build(fixture.body_positions, fixture.body_quaternions, WAND)
    assert [f.message for f in moved.findings] == [f.message for f in here.findings]
    assert {(f.kind, f.sensors) for f in here.findings} == {("swapped", (0, 3)), ("rotated", (5,))}


def test_a_five_dof_sensor_may_roll_about_its_axis_but_not_tilt():
    wand = wand_layout("aurora-5dof")
    axis = wand.sensor.axis
    roll = np.zeros(3)
    roll[axis] = 1.0
    tilt = np.zeros(3)
    tilt[(axis + 1) % 3] = np.radians(3)
    fixture = rig.build_fixture(wand, np.random.default_rng(1), turns={2: roll, 6: tilt})
    report = check_build(fixture.body_positions, fixture.body_quaternions, wand)
    assert [(f.kind, f.sensors) for f in report.findings] == [("rotated", (6,))]


@pytest.mark.parametrize("kind", ["cube", "wand"])
def test_random_builds_flag_every_fault_and_nothing_on_correct_ones(kind):
    """The benchmark runs 100 builds of each (benchmarks/bench_printing.py); a few here, default scene noise."""
    geometry = CUBE if kind == "cube" else WAND
    simulator = Simulator(load_scene("default"), seed=6, cube_geometry=CUBE, wand_geometry=WAND)
    rng = np.random.default_rng(11)
    tolerances = Tolerances()
    for _ in range(12):
        origin = None if kind == "cube" else geometry.positions[0]
        fixture, faults = rig.random_build(geometry, rng, origin=origin)
        setattr(simulator, kind, fixture)
        calibration = _calibrate_cube(simulator, 100) if kind == "cube" else _calibrate_wand(simulator, 100)
        report = check_cube(calibration, geometry) if kind == "cube" else check_wand(calibration, geometry)
        position, angle = rig.build_deviations(geometry, fixture, origin)
        must = (position > 1e-3) | (angle > np.radians(2))
        clean = (position < 0.5e-3) & (angle < np.radians(1))
        flagged = np.zeros(geometry.n_sensors, bool)
        for finding in report.findings:
            flagged[list(finding.sensors)] = True
        assert np.all(flagged[must]) and not np.any(flagged[clean]), (faults, report.render())
        for pair in faults["swaps"]:
            assert ("swapped", tuple(sorted(pair))) in {(f.kind, f.sensors) for f in report.findings}
        if not (faults["swaps"] or faults["turns"] or faults["lifts"]):
            assert report.ok  # a correct build passes silently
        assert tolerances.position < 1e-3 and tolerances.angle < np.radians(2)


def test_check_session_checks_the_calibrations_a_session_has():
    simulator = Simulator(_free_scene(), seed=1, cube_geometry=CUBE, wand_geometry=WAND)
    session = simulator.protocol({"cube_calibration": 100, "wand_calibration": 100},
                                 steps=["cube_calibration", "wand_calibration"])
    reports = check_session(session, {"cube": CUBE, "wand": WAND})
    assert [r.kind for r in reports] == ["cube", "wand"] and all(r.ok for r in reports)
    assert check_session(session, {}) == []


def test_the_cube_file_is_the_ideal_cube_of_the_fixture_model():
    from ivc.fixtures.cube import placed_vertices
    from ivc.fixtures.mapping import FixtureModel

    printed = cube_layout("liberty-rx2", 0.06)
    simulator = Simulator(_free_scene(), seed=1, cube_geometry=printed)
    session = simulator.protocol({"cube_calibration": 100, "cube_survey": 20, "wand_calibration": 100},
                                 steps=["cube_calibration", "cube_survey", "wand_calibration"])
    nominal = printed.in_declared_frame()[0]
    model = FixtureModel.from_session(session, "ideal", nominal=nominal)
    survey = session.steps["cube_survey"].attrs
    declared = survey["declared_position"], survey["declared_quaternion"]
    assert np.allclose(model.placement.positions, placed_vertices(nominal, declared))
    assert np.allclose(model.cube.vertices("ideal")[7], [0.06, 0.06, 0.06])
    assert np.allclose(FixtureModel.from_session(session, "ideal").cube.vertices("ideal")[7], 0.0508)
