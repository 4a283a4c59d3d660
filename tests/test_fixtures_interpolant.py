import numpy as np

from ivc.fixtures import CUBE_BITS
from ivc.fixtures.interpolant import TrilinearField


def skewed_cube(rng):
    rotation = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    return np.array([0.5, 0.02, -0.01]) + (0.0508 * CUBE_BITS + 0.002 * rng.standard_normal((8, 3))) @ rotation.T


def test_local_coordinates_invert_the_trilinear_map(rng):
    vertices = skewed_cube(rng)
    field = TrilinearField(vertices, np.zeros((8, 3, 3)))
    np.testing.assert_allclose(field.local(vertices), CUBE_BITS, atol=1e-12)
    uvw = rng.uniform(-0.2, 1.2, (500, 3))
    from ivc.fixtures.interpolant import _weights

    points = np.einsum("fn,ni->fi", _weights(uvw)[0], vertices)
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
    _, dg = field.value_and_jacobian(points)
    h = 1e-6
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        numeric = (field(points + step) - field(points - step)) / (2 * h)
        assert np.abs(dg[..., k] - numeric).max() < 1e-6 * np.abs(dg).max()
