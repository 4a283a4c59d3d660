"""The compiled pose inside the cube against the batched NumPy solver (ivc.pose.solve_pose)."""

import numpy as np
import pytest

from ivc.errors import InputError
from ivc.fixtures.cube_pose import solve_in_cube
from ivc.fixtures.interpolant import TrilinearField
from ivc.fixtures.mapping import FixtureModel
from ivc.pose import dipole_plus, solve_pose


@pytest.fixture(scope="module")
def cube(small_session):
    _, session = small_session
    model = FixtureModel.from_session(session)
    signal = session.steps["wand_sweep"].signal_matrices()[:, 0]
    return model, signal, model.placement.positions.mean(axis=0)


def test_compiled_cube_solve_equals_numpy_on_a_batch(cube):
    model, signal, centre = cube
    compiled = solve_in_cube(signal, model.interpolant, centre)
    reference = solve_pose(signal, dipole_plus(model.interpolant.value_and_jacobian), np.tile(centre, (len(signal), 1)))
    assert compiled.converged.mean() > 0.99
    np.testing.assert_array_equal(compiled.converged, reference.converged)
    ok = reference.converged
    np.testing.assert_allclose(compiled.position[ok], reference.position[ok], rtol=0, atol=1e-9)
    np.testing.assert_allclose(compiled.rotation[ok], reference.rotation[ok], rtol=0, atol=1e-9)
    for name in ("residual", "position_sigma", "angle_sigma"):
        np.testing.assert_allclose(getattr(compiled, name)[ok], getattr(reference, name)[ok], rtol=1e-6)


def test_compiled_basis_equals_the_interpolants(rng):
    import numba

    from ivc.fixtures.interpolant import harmonic_gradients
    from ivc.fixtures.kernels import cube_basis

    @numba.njit
    def basis(x, G, H):
        for n in range(len(x)):
            cube_basis(x[n, 0], x[n, 1], x[n, 2], G[n], H[n])

    x = rng.standard_normal((50, 3))
    G, H = np.empty((50, 15, 3)), np.empty((50, 15, 3, 3))
    basis(x, G, H)
    G_ref, H_ref = harmonic_gradients(x)
    np.testing.assert_allclose(G, G_ref, atol=1e-14)
    np.testing.assert_allclose(H, H_ref, atol=1e-14)


def test_bad_frames_and_bad_input(cube):
    model, signal, centre = cube
    S = signal[:4].copy()
    S[1, 0, 0] = np.nan
    start = np.tile(centre, (4, 1))
    start[2] = np.inf
    out = solve_in_cube(S, model.interpolant, start)
    assert list(out.converged) == [True, False, False, True]
    assert np.all(np.isnan(out.position[1:3])) and np.all(np.isnan(out.residual[1:3]))
    with pytest.raises(InputError, match="shape"):
        solve_in_cube(signal[:4, 0], model.interpolant, centre)
    with pytest.raises(InputError, match="HarmonicField"):
        solve_in_cube(S, TrilinearField(model.interpolant.vertices, model.interpolant.fields), centre)
