import numpy as np

from ivc.fixtures import CUBE_BITS
from ivc.fixtures.interpolant import TrilinearField


def skewed_cube(rng):
    rotation = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    return np.array([0.5, 0.02, -0.01]) + (0.0508 * CUBE_BITS + 0.002 * rng.standard_normal((8, 3))) @ rotation.T


def assert_jacobian_matches_differences(field, points, h=1e-6):
    """The analytic ∂g/∂r of ``field`` agrees with central differences to 1e-6; returns it."""
    _, dg = field.value_and_jacobian(points)
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        numeric = (field(points + step) - field(points - step)) / (2 * h)
        assert np.abs(dg[..., k] - numeric).max() < 1e-6 * np.abs(dg).max()
    return dg


def test_local_coordinates_invert_the_trilinear_map(rng):
    vertices = skewed_cube(rng)
    field = TrilinearField(vertices, np.zeros((8, 3, 3)))
    np.testing.assert_allclose(field.local(vertices), CUBE_BITS, atol=1e-12)
    uvw = rng.uniform(-0.2, 1.2, (500, 3))
    from ivc.fixtures.interpolant import trilinear_weights

    points = np.einsum("fn,ni->fi", trilinear_weights(uvw)[0], vertices)
    np.testing.assert_allclose(field.local(points), uvw, atol=1e-11)
    inside = field.inside(points)
    np.testing.assert_array_equal(inside, np.all((uvw >= 0) & (uvw <= 1), axis=1))


def test_linear_field_is_reproduced_exactly(rng):
    vertices = skewed_cube(rng)
    A, B = rng.standard_normal((3, 3)), rng.standard_normal((3, 3, 3))
    true = lambda r: A + np.einsum("ijk,...k->...ij", B, r)  # noqa: E731
    field = TrilinearField(vertices, true(vertices))
    points = vertices.mean(axis=0) + 0.02 * rng.standard_normal((200, 3))
    np.testing.assert_allclose(field(points), true(points), atol=1e-12)
    _, dg = field.value_and_jacobian(points)
    np.testing.assert_allclose(dg, np.broadcast_to(B, dg.shape), atol=1e-10)


def test_jacobian_against_central_differences(rng):
    vertices = skewed_cube(rng)
    field = TrilinearField(vertices, rng.standard_normal((8, 3, 3)))
    points = vertices.mean(axis=0) + 0.015 * rng.standard_normal((100, 3))
    assert_jacobian_matches_differences(field, points)


def test_harmonic_field_is_curl_and_divergence_free_and_exact_for_its_basis(rng):
    from ivc.fixtures.interpolant import HarmonicField, harmonic_gradients

    vertices = skewed_cube(rng)
    centre = vertices.mean(axis=0)
    scale = np.linalg.norm(vertices[7] - vertices[0]) / np.sqrt(3)
    coefficients = rng.standard_normal((15, 3))

    def true(r):
        return np.einsum("...bi,bj->...ij", harmonic_gradients((r - centre) / scale)[0], coefficients)

    field = HarmonicField(vertices, true(vertices))
    points = centre + 0.02 * rng.standard_normal((100, 3))
    np.testing.assert_allclose(field(points), true(points), atol=1e-10)
    dg = assert_jacobian_matches_differences(field, points)
    divergence = np.einsum("fiji->fj", dg)
    curl = np.stack([dg[:, 2, :, 1] - dg[:, 1, :, 2], dg[:, 0, :, 2] - dg[:, 2, :, 0], dg[:, 1, :, 0] - dg[:, 0, :, 1]])
    assert np.abs(divergence).max() < 1e-10 * np.abs(dg).max() and np.abs(curl).max() < 1e-10 * np.abs(dg).max()


def test_harmonic_beats_trilinear_on_a_real_field(rng):
    # the field of an image dipole 0.6 m below: smooth and harmonic, with curvature across the cube
    from ivc import dipole
    from ivc.fixtures.interpolant import HarmonicField

    def true(r):
        return dipole.field(r - [0.0, 0.0, -0.6]) @ np.diag([1.0, 1.0, -1.0])

    vertices = skewed_cube(rng)
    points = vertices.mean(axis=0) + 0.012 * rng.standard_normal((500, 3))
    reference = np.abs(true(points)).max()
    errors = {cls.__name__: np.abs(cls(vertices, true(vertices))(points) - true(points)).max() / reference
              for cls in (TrilinearField, HarmonicField)}
    assert errors["HarmonicField"] < 0.2 * errors["TrilinearField"]
