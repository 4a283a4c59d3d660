"""Extension sweeps solved as a rigid wand (ivc.lut.joint): exact poses with the true field, anywhere in the box."""

import numpy as np
import pytest

from ivc import rotations
from ivc.errors import InputError
from ivc.fixtures.wand import WandCalibration
from ivc.lut.fit_sources import SourceModel
from ivc.lut.joint import JointOptions, seed_from_sensors, solve_wand
from ivc.session import SessionError
from ivc.sim import Simulator
from ivc.sim.scene import NoiseSpec, scene_from_dict

#: a head box with ferrous objects just beyond its faces: its field is exactly that of point dipoles
BOX_SCENE = {
    "name": "box", "volume": {"center": [0.55, 0.0, 0.0], "size": [0.8, 0.6, 0.5]},
    "cube": {"center": [0.55, 0.0, 0.0]}, "extension": {"sweeps": 2, "frames": 3000, "speed": 0.4},
    "ferrous": [{"position": [1.03, 0.1, 0.0], "radius_mm": 40, "permeability": 1000},
                {"position": [0.5, -0.38, -0.1], "radius_mm": 30, "permeability": 1000},
                {"position": [0.3, 0.2, -0.33], "radius_mm": 35, "permeability": 1000}],
}


def true_field(scene) -> SourceModel:
    """The spheres' induced dipoles as a SourceModel: m = a³ K f_D(c) for each source coil."""
    positions = np.array([s.position for s in scene.spheres])
    moments = np.array([s.radius**3 * (s.permeability - 1) / (s.permeability + 2) * _fd(s.position)
                        for s in scene.spheres])
    return SourceModel(positions, moments)


def _fd(c):
    from ivc import dipole

    return dipole.field(np.asarray(c, float))


@pytest.fixture(scope="module")
def simulated():
    scene = scene_from_dict(BOX_SCENE)
    scene.noise = NoiseSpec.none()
    sim = Simulator(scene, seed=3)
    calibration, _ = sim.step("wand_calibration", 5)
    wand = WandCalibration.from_step(calibration)
    step, truth = sim.step("extension_sweep_1", 3000)
    return scene, wand, step, truth


def test_the_source_model_is_the_simulated_field(simulated):
    scene, _, step, truth = simulated
    field = scene.secondary_field()
    points = truth.position[::50].reshape(-1, 3)
    np.testing.assert_allclose(true_field(scene)(points), field(points), rtol=1e-12, atol=1e-15)


def test_extension_sweep_gives_the_true_wand_poses_anywhere_in_the_box(simulated):
    scene, wand, step, truth = simulated
    S = step.signal_matrices()
    true_r0 = truth.position[:, 0]
    true_T0 = rotations.to_matrix(truth.quaternion[:, 0])
    # the walk covers the box: sensors from near the cube to the faces
    distance = np.linalg.norm(truth.position - scene.cube.center, axis=-1)
    assert distance.max() > 0.4 and np.all(truth.position >= scene.volume.lower - 1e-9)
    rng = np.random.default_rng(0)
    start_r = true_r0 + 0.003 * rng.standard_normal(true_r0.shape)
    start_T = true_T0 @ rotations.to_matrix(rotations.from_rotvec(0.01 * rng.standard_normal(true_r0.shape)))
    model = true_field(scene)
    for use in (np.ones(S.shape[:2], bool), np.arange(S.shape[1])[None, :] >= S.shape[1] - 2):
        use = np.broadcast_to(use, S.shape[:2]).copy()
        solution = solve_wand(S, use, wand, model.value_and_jacobian, start_r, start_T)
        assert solution.converged.all()
        positions, rots = wand.propagate(solution.position, solution.rotation)
        assert np.max(np.linalg.norm(positions - truth.position, axis=-1)) < 1e-6
        assert np.max(np.abs(rots - rotations.to_matrix(truth.quaternion))) < 1e-6


def test_seed_from_a_corrected_sensor_inverts_the_wand_calibration(simulated):
    _, wand, _, truth = simulated
    trusted = np.zeros(truth.position.shape[:2], bool)
    trusted[:, 5] = True
    trusted[:10] = False
    r0, T0 = seed_from_sensors(truth.position, truth.quaternion, trusted, np.zeros(trusted.shape), wand)
    assert np.all(np.isnan(r0[:10]))
    np.testing.assert_allclose(r0[10:], truth.position[10:, 0], atol=1e-12)
    np.testing.assert_allclose(T0[10:], rotations.to_matrix(truth.quaternion[10:, 0]), atol=1e-12)


def test_options_and_sessions_are_checked():
    with pytest.raises(Exception, match="max_residual"):
        JointOptions(max_residual=float("nan"))
    with pytest.raises(Exception, match="error_floor"):
        JointOptions(error_floor=0.0)
    for few in (0, 99, 5000.0):  # below what a sources fit takes, or not a whole number
        with pytest.raises(InputError, match="max_samples"):
            JointOptions(max_samples=few)
    from ivc.lut.joint import fit_joint
    from ivc.session import Session

    with pytest.raises(SessionError, match="no extension sweeps"):
        fit_joint(Session(hemisphere="+x"))


def test_compiled_wand_solve_equals_the_numpy_form(simulated):
    """solve_wand_table (numba) against solve_wand (NumPy) on a tabulated field: same poses to 1e-9 m."""
    from ivc.lut.joint import solve_wand_table
    from ivc.table.grid import Grid, GridField

    scene, wand, step, truth = simulated
    S = step.signal_matrices()[::5]
    true_r0, q0 = truth.position[::5, 0], truth.quaternion[::5, 0]
    grid = Grid.around(truth.position.reshape(-1, 3), 0.0381)
    table = GridField(grid, true_field(scene)(grid.nodes()), np.ones(grid.shape, bool))
    rng = np.random.default_rng(1)
    start_r = true_r0 + 0.003 * rng.standard_normal(true_r0.shape)
    start_T = rotations.to_matrix(q0) @ rotations.to_matrix(rotations.from_rotvec(0.01 * rng.standard_normal(
        true_r0.shape)))
    use = rng.random(S.shape[:2]) < 0.6
    use[:3] = False  # frames with no used sensor come back NaN
    start_r[3:5] = np.nan  # and so do frames without a start
    numpy_form = solve_wand(S, use, wand, table.value_and_jacobian, start_r, start_T)
    compiled = solve_wand_table(S, use, wand, table, start_r, start_T)
    assert compiled.converged.sum() > 0.9 * len(S)
    np.testing.assert_array_equal(compiled.converged, numpy_form.converged)
    ok = compiled.converged
    assert np.all(np.isnan(compiled.position[:5]))
    np.testing.assert_allclose(compiled.position[ok], numpy_form.position[ok], rtol=0, atol=1e-9)
    np.testing.assert_allclose(compiled.rotation[ok], numpy_form.rotation[ok], rtol=0, atol=1e-9)
    np.testing.assert_allclose(compiled.residual[ok], numpy_form.residual[ok], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(compiled.position_sigma[ok], numpy_form.position_sigma[ok], rtol=1e-6, atol=1e-15)
    np.testing.assert_allclose(compiled.angle_sigma[ok], numpy_form.angle_sigma[ok], rtol=1e-6, atol=1e-15)
    with pytest.raises(Exception, match="GridField"):
        solve_wand_table(S, use, wand, table.value_and_jacobian, start_r, start_T)
    with pytest.raises(Exception, match="starting poses"):
        solve_wand_table(S, use, wand, table, start_r[:-1], start_T)


def test_the_table_is_finer_than_its_support_grid_and_maps_the_same_volume():
    """A subdivided grid keeps the coarse nodes (same validity and support there); a fine node is valid when the
    coarse nodes around it are, so the mapped volume is the coarse grid's; the default table is twice as fine."""
    from ivc.lut.joint import mapped_litres, subdivided
    from ivc.table.grid import Grid

    grid = Grid(np.array([0.1, -0.2, 0.0]), 0.04, (5, 4, 4))
    valid = np.ones(grid.shape, dtype=bool)
    valid[4, 3, 3] = valid[0, 0, 1] = False
    support = np.arange(grid.size).reshape(grid.shape)
    fine, fine_valid, fine_support = subdivided(grid, valid, support, 2)
    assert fine.shape == (9, 7, 7) and fine.spacing == pytest.approx(0.02)
    np.testing.assert_allclose(fine.nodes()[::2, ::2, ::2], grid.nodes())
    np.testing.assert_array_equal(fine_valid[::2, ::2, ::2], valid)
    np.testing.assert_array_equal(fine_support[::2, ::2, ::2], support)
    assert not fine_valid[7, 5, 5] and fine_valid[6, 4, 4]  # the cell holding an invalid corner
    assert fine_support[1, 1, 1] == support[:2, :2, :2].min()
    assert mapped_litres(fine, fine_valid) == pytest.approx(mapped_litres(grid, valid))
    assert subdivided(grid, valid, support, 1)[0] is grid
    assert JointOptions().table_subdivision == 2
    with pytest.raises(InputError):
        JointOptions(table_subdivision=0)
    with pytest.raises(InputError):
        JointOptions(even_cell=-1.0)
