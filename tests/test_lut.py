"""The look-up table: grid, interpolation, harmonic basis, fits, refinement, file."""

import numpy as np
import pytest

from ivc import dipole, rotations
from ivc.lut import FitOptions, Grid, GridField, LookupTable, LutError, fit_lut, harmonics, read, write
from ivc.lut.fit_harmonic import fit_harmonic
from ivc.lut.fit_poly import fit_poly
from ivc.lut.support import node_support
from ivc.session import SessionError
from ivc.table.grid import fill_invalid
from tests.helpers import CENTRE, ball, external_dipole_field, quadratic_field, samples_of

# --- harmonic basis -------------------------------------------------------------------------------------------

def test_harmonic_gradients_are_curl_and_divergence_free(rng):
    x = rng.uniform(-0.8, 0.8, (50, 3))
    h = 1e-6
    J = np.stack([(harmonics.gradients(x + h * e, 6) - harmonics.gradients(x - h * e, 6)) / (2 * h)
                  for e in np.eye(3)], axis=-1)  # (N, K, 3, 3): ∂(∇Φ)_i/∂x_k
    scale = np.abs(J).max()
    assert np.abs(J - np.swapaxes(J, -1, -2)).max() < 1e-6 * scale  # curl-free
    assert np.abs(np.einsum("nkii->nk", J)).max() < 1e-6 * scale  # divergence-free (Φ harmonic)
    assert harmonics.gradients(x, 6).shape == (50, harmonics.count(6), 3)


def test_harmonic_basis_of_lower_degree_is_a_prefix_and_independent(rng):
    x = rng.uniform(-1, 1, (400, 3))
    low, high = harmonics.gradients(x, 3), harmonics.gradients(x, 5)
    np.testing.assert_array_equal(low, high[:, : harmonics.count(3)])
    design = high.transpose(0, 2, 1).reshape(-1, harmonics.count(5))
    assert np.linalg.matrix_rank(design) == harmonics.count(5)


# --- grid and interpolation ------------------------------------------------------------------------------------

def test_grid_index_is_eq_105_and_grid_covers_its_points(rng):
    grid = Grid([0.3, -0.2, -0.2], 0.05, (4, 5, 6))
    i, j, k = np.meshgrid(*(np.arange(n) for n in grid.shape), indexing="ij")
    np.testing.assert_array_equal(grid.flat_index(i, j, k).ravel(), np.arange(grid.size))
    np.testing.assert_allclose(grid.nodes()[1, 2, 3], [0.35, -0.1, -0.05])
    points = ball(rng, 500, 0.2)
    around = Grid.around(points, 0.0381)
    assert around.contains(points).all()
    # one whole cell of margin on every face
    assert np.all(points.min(axis=0) - around.origin >= 0.0381 - 1e-12)
    far = around.origin + 0.0381 * (np.array(around.shape) - 1)
    assert np.all(far - points.max(axis=0) >= 0.0381 - 1e-12)
    with pytest.raises(ValueError, match="spacing"):
        Grid([0, 0, 0], 0.0, (3, 3, 3))


def test_cubic_interpolation_is_exact_for_quadratics_and_its_gradient_is_the_derivative(rng):
    grid = Grid(CENTRE - 0.2, 0.04, (11, 11, 11))
    table = GridField(grid, quadratic_field(grid.nodes().reshape(-1, 3)).reshape(*grid.shape, 3, 3),
                      np.ones(grid.shape, bool))
    inner = ball(rng, 300, 0.14)  # away from the boundary cells, whose ghost nodes are extrapolated
    g, dg, mapped = table.evaluate(inner)
    assert mapped.all()
    np.testing.assert_allclose(g, quadratic_field(inner), atol=1e-12 * np.abs(g).max())
    h = 1e-6
    fd = np.stack([(table(inner + h * e) - table(inner - h * e)) / (2 * h) for e in np.eye(3)], axis=-1)
    np.testing.assert_allclose(dg, fd, atol=1e-6 * np.abs(dg).max())
    linear = GridField(grid, table._padded[1:-1, 1:-1, 1:-1].reshape(*grid.shape, 3, 3), np.ones(grid.shape, bool),
                       "linear")
    nodes = grid.nodes()[3:6, 3:6, 3:6].reshape(-1, 3)
    np.testing.assert_allclose(linear(nodes), quadratic_field(nodes), atol=1e-13)


def test_points_outside_the_grid_or_near_invalid_nodes_are_not_mapped():
    grid = Grid([0, 0, 0], 0.1, (4, 4, 4))
    valid = np.ones(grid.shape, bool)
    valid[3, 3, 3] = False
    table = GridField(grid, np.ones((*grid.shape, 3, 3)), valid)
    _, _, mapped = table.evaluate(np.array([[0.15, 0.15, 0.15], [0.25, 0.25, 0.25], [-0.01, 0.1, 0.1],
                                            [0.1, 0.1, 0.31], [np.nan, 0.1, 0.1]]))
    np.testing.assert_array_equal(mapped, [True, False, False, False, False])


def test_fill_invalid_extends_linear_data_linearly():
    grid = Grid([0, 0, 0], 1.0, (5, 5, 5))
    values = grid.nodes() @ np.array([1.0, -2.0, 0.5])
    valid = np.zeros(grid.shape, bool)
    valid[1:4, 1:4, 1:4] = True
    filled = fill_invalid(values[..., None], valid)[..., 0]
    expected = Grid([-1, -1, -1], 1.0, (7, 7, 7)).nodes() @ np.array([1.0, -2.0, 0.5])
    np.testing.assert_allclose(filled[1:-1, 1:-1, 1:-1][valid], values[valid])
    # every node one step from the valid block is an exact linear extrapolation
    near = np.zeros((7, 7, 7), bool)
    near[1:6, 1:6, 1:6] = True
    np.testing.assert_allclose(filled[near], expected[near], atol=1e-12)


def test_node_support_counts_samples_in_the_eight_cells_around_a_node():
    grid = Grid([0, 0, 0], 1.0, (3, 3, 3))
    support = node_support(grid, np.array([[0.5, 0.5, 0.5], [1.5, 1.5, 1.5], [5, 5, 5]]))
    assert support[1, 1, 1] == 2 and support[0, 0, 0] == 1 and support[2, 2, 2] == 1 and support[2, 0, 0] == 0


# --- fits -------------------------------------------------------------------------------------------------------

def test_harmonic_fit_reproduces_a_known_harmonic_field_at_and_between_nodes(rng):
    # noiseless samples of an external-dipole field (~10 % of the primary) in a 0.2 m ball. Tolerance, as a
    # fraction of the primary field |f_D| at the point (what a pose error is made of): 2e-5 at the nodes
    # inside the data, and 2e-4 between them through cubic interpolation on the 38.1 mm grid (~0.03 mm)
    samples = samples_of(external_dipole_field, ball(rng, 20_000, 0.2))
    model, report = fit_harmonic(samples)
    grid = Grid.around(samples.positions, 0.0381)
    values = model(grid.nodes())
    nodes = grid.nodes().reshape(-1, 3)
    inside = np.linalg.norm(nodes - CENTRE, axis=1) < 0.19

    def relative(G, r):
        return np.linalg.norm(G - external_dipole_field(r), axis=(1, 2)) / np.linalg.norm(dipole.field(r), axis=(1, 2))

    assert relative(values.reshape(-1, 3, 3)[inside], nodes[inside]).max() < 2e-5
    between = ball(rng, 2000, 0.17)
    table = GridField(grid, values, np.ones(grid.shape, bool))
    assert relative(table(between), between).max() < 2e-4
    assert np.median(np.linalg.norm(samples.fields, axis=(1, 2)) / np.linalg.norm(
        dipole.field(samples.positions), axis=(1, 2))) > 0.03  # a field worth mapping
    assert report["degree"] >= 4 and report["cv_rms_mm"] < 1e-3  # noiseless: tiny held-out residual


def test_harmonic_fit_downweights_outliers(rng):
    positions = ball(rng, 20_000, 0.2)
    samples = samples_of(quadratic_field, positions)
    samples.fields[::50] += 0.2 * np.abs(samples.fields).max()  # 2 % gross outliers
    model, report = fit_harmonic(samples, degree=3)
    clean = ball(rng, 500, 0.18)
    assert np.abs(model(clean) - quadratic_field(clean)).max() < 1e-3 * np.abs(samples.fields).max()
    assert report["outliers_downweighted"] >= 0.9 * len(samples) / 50


def test_poly_fit_reproduces_a_smooth_field_at_supported_nodes(rng):
    samples = samples_of(quadratic_field, ball(rng, 40_000, 0.2))
    grid = Grid.around(samples.positions, 0.0381)
    values = fit_poly(samples, grid, degree=2)
    fitted = np.all(np.isfinite(values.reshape(*grid.shape, 9)), axis=-1)
    assert fitted.sum() > 100
    nodes = grid.nodes()[fitted]
    np.testing.assert_allclose(values[fitted], quadratic_field(nodes), atol=1e-9 * np.abs(samples.fields).max())
    # nodes whose neighbourhood is one-sided (the edge of the data) are left unfitted, never extrapolated
    assert not fitted[0, 0, 0]


# --- from a session ---------------------------------------------------------------------------------------------

def test_fit_refuses_a_session_with_missing_steps(small_session):
    _, session = small_session
    partial = type(session)(session.hemisphere, {k: v for k, v in session.steps.items() if k != "wand_calibration"})
    with pytest.raises(SessionError, match="wand_calibration.*ivc collect wand_calibration"):
        fit_lut(partial)


def test_fit_refuses_too_few_kept_samples_and_names_the_step_to_redo(small_session):
    _, session = small_session
    sweep = session.steps["wand_sweep"]
    moved = session.select_frames("wand_sweep", slice(None))
    moved.steps["wand_sweep"].signal = sweep.signal * 1.3  # sensor 0 no longer matches the cube field
    with pytest.raises(SessionError, match="redo `ivc collect cube_survey`|keeping wand sensor 0"):
        fit_lut(moved)


@pytest.mark.slow
def test_fit_and_refinement_on_a_simulated_session(small_session, tmp_path):
    simulator, session = small_session
    table = fit_lut(session, FitOptions(refine=True, max_refinements=2, min_support=5))
    assert table.fit["samples"]["kept"] > 0.99 * table.fit["samples"]["total"]
    assert 1 <= len(table.fit["refinement"]) <= 2 and table.fit["cv_rms_mm"] < 1.0
    # the map is the scene's field, seen in the declared frame (where it was measured): compare where mapped
    field = table.field()
    nodes = table.grid.nodes()[table.valid]
    r0_true, T_true = simulator.true_cube_frame()
    survey = session.steps["cube_survey"]
    D = rotations.to_matrix(survey.attrs["declared_quaternion"]) @ T_true.T
    true_points = (nodes - (survey.attrs["declared_position"] - D @ r0_true)) @ D  # declared -> true frame
    # the map also absorbs the f_D mismatch of the declared-pose error, so agreement is to a few % only
    primary = np.linalg.norm(dipole.field(nodes), axis=(1, 2))
    mismatch = np.linalg.norm(field(nodes) - D @ simulator.secondary(true_points) @ D.T, axis=(1, 2)) / primary
    assert np.median(mismatch) < 0.02
    path = tmp_path / "map.h5"
    write(table, path)
    back = read(path)
    np.testing.assert_array_equal(back.values, table.values)
    np.testing.assert_array_equal(back.valid, table.valid)
    assert back.fit == table.fit and back.provenance == table.provenance and back.hemisphere == table.hemisphere
    np.testing.assert_array_equal(back.grid.origin, table.grid.origin)
    assert (back.grid.spacing, back.grid.shape) == (table.grid.spacing, table.grid.shape)
    with pytest.raises(FileExistsError):
        write(table, path)


def test_reading_something_that_is_not_a_table_fails_clearly(tmp_path, small_session):
    from ivc import session as session_io

    _, session = small_session
    path = tmp_path / "session.h5"
    session_io.write(session, path)
    with pytest.raises(LutError, match="not an ivc look-up table"):
        read(path)
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    with pytest.raises(LutError, match="not an HDF5 file"):
        read(tmp_path / "junk.h5")
    with pytest.raises(LutError, match="no valid node"):
        LookupTable(Grid([0, 0, 0], 0.1, (2, 2, 2)), np.zeros((2, 2, 2, 3, 3)), np.zeros((2, 2, 2), bool),
                    np.zeros((2, 2, 2), int))
