"""Physics of the simulated room: eddy currents, ferrous objects, the field's structure."""

import numpy as np
import pytest
from scipy import integrate

from ivc import dipole
from ivc.sim import builtin_scenes, eddy, load_scene, meshes
from ivc.sim.field import FerrousSphere


def test_triangle_potential_against_adaptive_quadrature():
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.8, 0.0]])
    area = 0.5 * np.linalg.norm(np.cross(tri[1] - tri[0], tri[2] - tri[0]))

    def reference(x):
        def integrand(v, u):
            y = tri[0] + u * (tri[1] - tri[0]) + v * (tri[2] - tri[0])
            return 2 * area / np.linalg.norm(x - y)

        return integrate.dblquad(integrand, 0, 1, 0, lambda u: 1 - u, epsabs=1e-11, epsrel=1e-11)[0]

    points = np.array([[0.4, 0.3, 0.5], [2.0, 1.0, 0.3], [0.4, 0.3, 0.05], [-0.5, 0.2, 0.0], [1.5, -0.2, -0.4]])
    got = eddy.triangle_potential(points, np.repeat(tri[None], len(points), axis=0))
    want = [reference(x) for x in points]
    np.testing.assert_allclose(got, want, rtol=1e-8)
    # the near-pair kernel is the area times the 7-point quadrature of that exact potential
    values = np.empty(1)
    corners = np.stack([tri, tri + [0.0, 0.0, 0.3]])
    eddy._near_pair_kernel(corners, np.array([1]), np.array([0]), eddy.QUAD_BARY, eddy.QUAD_WEIGHTS, values)
    quad_points = eddy.QUAD_BARY @ corners[1]
    expected = area * eddy.QUAD_WEIGHTS @ eddy.triangle_potential(quad_points, np.repeat(tri[None], 7, axis=0))
    np.testing.assert_allclose(values[0], expected, rtol=1e-12)


def test_self_integral_of_a_triangle():
    # ∫∫ 1/|r - r'| over an equilateral triangle of side a with itself: closed form a³ ln(3)·(1/√... )
    # here checked by its scaling law (a⁵ / a² ... = a³) and against a finer split of the triangle
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, np.sqrt(3) / 2, 0.0]])
    mesh = eddy.ConductorMesh(tri, np.array([[0, 1, 2]]), np.zeros(1), np.ones(3, bool))
    whole = eddy.face_integral_matrix(mesh)[0, 0]
    small = eddy.ConductorMesh(tri * 0.5, np.array([[0, 1, 2]]), np.zeros(1), np.ones(3, bool))
    assert eddy.face_integral_matrix(small)[0, 0] == pytest.approx(whole * 0.5**3, rel=1e-12)
    # the equilateral self term is (a³/2)·ln(3)·... known: 4A²/(3a)·ln(3)·... use subdivision instead
    fine = meshes.plate((1.0, 1.0), 0.25)  # sanity: symmetric, positive definite inductance
    conductor = eddy.ConductorMesh.from_parts([(fine, 0.0)])
    L = eddy.inductance_matrix(conductor)
    free = conductor.free
    np.testing.assert_allclose(L, L.T)
    assert np.all(np.linalg.eigvalsh(L[np.ix_(free, free)]) > 0)


def test_perfect_plate_gives_image_dipole():
    # a large thin perfectly conducting plate 0.15 m below the source: B·n = 0 on the plate, so near
    # its centre the secondary field is that of the image dipole at z = -0.3 with moment (mx, my, -mz)
    plate = meshes.plate((1.5, 1.5), 0.05)
    plate.apply_translation([0, 0, -0.15])
    mesh = eddy.ConductorMesh.from_parts([(plate, 0.0)])
    dipoles = eddy.FaceDipoles.from_solution(mesh, eddy.solve_stream_function(mesh, 1e4))
    points = np.array([[0.05, 0.03, -0.05], [0.0, 0.0, 0.05], [0.1, -0.05, -0.1], [-0.08, 0.06, 0.0]])
    G = dipoles.field(points)
    image = dipole.field(points - [0.0, 0.0, -0.3]) @ np.diag([1.0, 1.0, -1.0])
    error = np.linalg.norm(G - image, axis=(1, 2)) / np.linalg.norm(image, axis=(1, 2))
    assert np.all(error < 0.10), error


def test_resistive_sheet_is_weaker_than_perfect_and_tends_to_it():
    plate = meshes.plate((0.6, 0.6), 0.06)
    plate.apply_translation([0.4, 0, -0.2])
    point = np.array([[0.4, 0.0, 0.0]])

    def field(resistivity, frequency):
        mesh = eddy.ConductorMesh.from_parts([(plate, resistivity)])
        return eddy.FaceDipoles.from_solution(mesh, eddy.solve_stream_function(mesh, frequency)).field(point)[0]

    perfect = field(0.0, 1e4)
    aluminium = field(1 / (3.5e7 * 1e-3), 1e4)
    resistive = field(1 / (3.5e7 * 1e-5), 1e4)
    assert np.linalg.norm(resistive) < np.linalg.norm(aluminium) <= np.linalg.norm(perfect) * 1.0001
    assert np.linalg.norm(aluminium - perfect) < 0.05 * np.linalg.norm(perfect)  # 1 mm Al at 10 kHz: nearly perfect


def test_ferrous_sphere_is_an_induced_dipole():
    sphere = FerrousSphere(np.array([0.5, 0.2, 0.0]), 0.02, 1e6)
    x = np.array([0.6, -0.1, 0.05])
    primary = dipole.field(sphere.position)  # columns: the field at the sphere of each source coil
    moment = sphere.radius**3 * primary  # K -> 1 for large permeability
    np.testing.assert_allclose(sphere.field(x), dipole.field(x - sphere.position) @ moment, rtol=1e-5)


def _div_curl(field, x, h=1e-3):
    """Divergence (3,) and curl (3, 3) of each column of field at x, by central differences; and |∇G|."""
    grad = np.empty((3, 3, 3))  # [component i, source j, derivative k]
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        grad[:, :, k] = (field(x + step) - field(x - step)) / (2 * h)
    div = np.einsum("iji->j", grad)
    curl = np.stack([grad[2, :, 1] - grad[1, :, 2], grad[0, :, 2] - grad[2, :, 0], grad[1, :, 0] - grad[0, :, 1]])
    return div, curl, np.linalg.norm(grad)


@pytest.fixture(scope="module", params=builtin_scenes())
def scene_field(request):
    scene = load_scene(request.param)
    field = scene.secondary_field()
    # every check below looks within the mapped radius of the cube: a scene with a working volume (the cockpit)
    # is tabulated around the cube alone, at its own spacing (its whole box would cost 4x more and add nothing here)
    reach = scene.mapped_radius + 0.02
    field.roi = (scene.cube.center - reach, scene.cube.center + reach)
    return scene, field


def _inside_the_table(field, points):
    """Outside its table a SecondaryField falls back to the exact sum, which would make a check pass trivially."""
    lower, upper = field.roi
    assert np.all(points >= lower) and np.all(points <= upper)


@pytest.mark.slow
def test_secondary_field_is_divergence_and_curl_free(scene_field):
    scene, field = scene_field
    rng = np.random.default_rng(3)
    direction = rng.standard_normal((6, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = scene.cube.center + direction * scene.check_radius * rng.random((6, 1))
    _inside_the_table(field, np.concatenate([points - 1e-3, points + 1e-3]))
    for x in points:
        # exact sum of dipole fields: harmonic, so only the O(h²) difference error remains:
        # (h / distance to the nearest conductor)² ≈ (1 mm / 100 mm)² relative to |∇G|
        div, curl, scale = _div_curl(lambda p: field.exact(p[None])[0], x)
        assert np.abs(div).max() < 1e-3 * scale and np.abs(curl).max() < 1e-3 * scale
        # the tabulated field (cubic splines on a 1 cm grid) keeps this to the spline's derivative error,
        # ~(1 cm / distance)³ relative; 2 % bounds it for conductors >= 4 cm away
        div, curl, scale = _div_curl(lambda p: field(p[None])[0], x)
        assert np.abs(div).max() < 2e-2 * scale and np.abs(curl).max() < 2e-2 * scale


@pytest.mark.slow
def test_tabulated_field_matches_exact_sum(scene_field):
    scene, field = scene_field
    rng = np.random.default_rng(4)
    points = scene.cube.center + rng.uniform(-1, 1, (300, 3)) * scene.mapped_radius / np.sqrt(3)
    _inside_the_table(field, points)
    exact = field.exact(points)
    error = np.linalg.norm(field(points) - exact, axis=(1, 2)) / np.linalg.norm(dipole.field(points), axis=(1, 2))
    assert error.max() < 1e-3  # relative to the primary field


@pytest.mark.slow
def test_mesh_refinement_changes_field_little():
    # the default scene's panel, meshed at 40 mm and at 20 mm (4x the triangles)
    scene = load_scene("default")
    panel = scene.conductors[0]
    rng = np.random.default_rng(5)
    direction = rng.standard_normal((200, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = scene.cube.center + direction * scene.check_radius * rng.random((200, 1)) ** (1 / 3)
    fields = []
    for resolution in (0.04, 0.02):
        panel.resolution = resolution
        mesh = eddy.ConductorMesh.from_parts([(panel.mesh(), panel.surface_resistivity(scene.frequency_hz))])
        dipoles = eddy.FaceDipoles.from_solution(mesh, eddy.solve_stream_function(mesh, scene.frequency_hz))
        fields.append((len(mesh.faces), dipoles.field(points)))
    (coarse_faces, coarse), (fine_faces, fine) = fields
    assert fine_faces >= 3.5 * coarse_faces
    change = np.linalg.norm(fine - coarse, axis=(1, 2)) / np.linalg.norm(fine, axis=(1, 2))
    assert np.median(change) < 0.05 and np.percentile(change, 95) < 0.05


def test_box_mesh_is_closed_and_outward():
    mesh = meshes.box((0.3, 0.2, 0.05), 0.02)
    assert mesh.is_watertight and mesh.volume == pytest.approx(0.3 * 0.2 * 0.05, rel=1e-9)
    desk = meshes.desk((1.4, 0.8, 0.75), 0.05)
    assert len(desk.faces) > 0 and desk.bounds[1][2] == pytest.approx(0.0) and desk.bounds[0][2] == pytest.approx(-0.75)
    with pytest.raises(ValueError, match="unknown conductor shape"):
        meshes.build("sphere", (1, 1, 1), 0.1)


def test_a_tabulation_kept_in_the_field_cache_is_the_same_tabulation(tmp_path, monkeypatch):
    """IVC_FIELD_CACHE: the second tabulation of the same field loads the first one's bytes; a field that
    differs in its dipoles, region or spacing gets its own file; without the variable nothing is written."""
    from ivc.sim.eddy import FaceDipoles
    from ivc.sim.field import SecondaryField

    rng = np.random.default_rng(8)
    dipoles = FaceDipoles(rng.uniform(0.6, 0.8, (20, 3)), 1e-4 * rng.standard_normal((20, 3, 3)))
    roi = (np.array([0.2, -0.1, -0.1]), np.array([0.4, 0.1, 0.05]))
    monkeypatch.delenv("IVC_FIELD_CACHE", raising=False)
    plain = SecondaryField(dipoles, [], roi, spacing=0.02)
    plain.tabulate()
    monkeypatch.setenv("IVC_FIELD_CACHE", str(tmp_path))
    first = SecondaryField(dipoles, [], roi, spacing=0.02)
    first.tabulate()
    assert len(list(tmp_path.glob("field-*.npy"))) == 1
    calls = []
    again = SecondaryField(dipoles, [], roi, spacing=0.02)
    again.tabulate(progress=lambda done, total: calls.append((done, total)))
    assert calls == [(calls[0][1], calls[0][1])]  # loaded: progress goes straight to the end
    for field_ in (first, again):
        np.testing.assert_array_equal(field_._coefficients, plain._coefficients)
        np.testing.assert_array_equal(field_._origin, plain._origin)
    points = rng.uniform(roi[0], roi[1], (50, 3))
    np.testing.assert_array_equal(again(points), plain(points))
    moved = FaceDipoles(dipoles.centres + [0.0, 0.0, 1e-9], dipoles.moments)
    for other in (SecondaryField(moved, [], roi, 0.02), SecondaryField(dipoles, [], roi, 0.025),
                  SecondaryField(dipoles, [], (roi[0], roi[1] + 0.01), 0.02)):
        other.tabulate()
    assert len(list(tmp_path.glob("field-*.npy"))) == 4 and not list(tmp_path.glob("*.tmp"))
