"""Small inputs on a cold compile cache: the NumPy and interpreted forms equal the compiled kernels."""

import numpy as np
import pytest

from ivc import compiled, dipole, rotations
from ivc.correct import Corrector, PoseCorrector, pose_kernels
from ivc.correct import kernels as correct_kernels
from ivc.dipole import kernels as dipole_kernels
from ivc.dipole import numpy_kernels
from ivc.table import grid_numpy
from ivc.table import kernels as lut_kernels
from ivc.table.grid import Grid, GridField


def _table():
    """A small table of a smooth secondary field around (0.4, 0, 0) m, every node valid."""
    grid = Grid(np.array([0.3, -0.1, -0.1]), 0.05, (5, 5, 5))
    values = 0.01 * np.einsum("...i,jk->...jk", grid.nodes() - np.array([0.4, 0.0, 0.0]), np.ones((3, 3)))
    return GridField(grid, values, np.ones(grid.shape, bool))


@pytest.fixture
def poses(rng):
    r = np.array([0.4, 0.0, 0.0]) + 0.05 * rng.standard_normal((200, 3))
    T = rotations.to_matrix(rotations.canonical(rng.standard_normal((200, 4))))
    return r, T


def test_numpy_dipole_kernels_equal_the_compiled_ones(poses):
    r, T = poses
    for name, args in (("field_kernel", (r,)), ("signal_kernel", (r, T))):
        compiled_out, numpy_out = np.empty((len(r), 3, 3)), np.empty((len(r), 3, 3))
        getattr(dipole_kernels, name)(*args, compiled_out)
        getattr(numpy_kernels, name)(*args, numpy_out)
        np.testing.assert_allclose(numpy_out, compiled_out, rtol=1e-12, atol=0)
    S = dipole.signal(r, T) + 0.3 * dipole.field(r) * np.linspace(0, 1, len(r))[:, None, None]
    S[100:105] = -S[100:105]  # det K < 0: the SVD branch (distinct singular values: a secondary field)
    S[5, 0, 0] = np.nan  # not finite: NaN out
    h = np.array([1.0, 0.0, 0.0])
    out_c = np.empty((len(r), 3)), np.empty((len(r), 3, 3))
    out_n = np.empty((len(r), 3)), np.empty((len(r), 3, 3))
    dipole_kernels.closed_form_pose_kernel(S, h, *out_c)
    numpy_kernels.closed_form_pose_kernel(S, h, *out_n)
    for a, b in zip(out_n, out_c, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12, equal_nan=True)
    assert np.isnan(out_n[1][5]).all()


@pytest.mark.parametrize("cubic", [True, False])
def test_numpy_grid_kernel_equals_the_compiled_one(rng, cubic):
    field = _table()
    points = field.grid.origin + rng.uniform(-0.05, 0.25, (500, 3))  # inside, outside and on no cell
    points[0] = field.grid.origin  # a node: zero weights skipped
    points[1] = np.nan
    padded, valid_cells, origin, spacing, shape, _ = field.kernel_grid
    args = ((padded, valid_cells, origin, spacing, shape, cubic), points)
    C = padded.shape[3]
    out_c = np.empty((len(points), C)), np.empty((len(points), C, 3)), np.empty(len(points), bool)
    out_n = np.empty((len(points), C)), np.empty((len(points), C, 3)), np.empty(len(points), bool)
    lut_kernels.grid_kernel(*args, *out_c)
    grid_numpy.grid_kernel(*args, *out_n)
    for a, b in zip(out_n[:2], out_c[:2], strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15, equal_nan=True)
    np.testing.assert_array_equal(out_n[2], out_c[2])
    assert out_n[2][2:].any() and not out_n[2][2:].all()


def _cold(monkeypatch):
    """As on a fresh install: no kernel is ready, small inputs use the stand-ins."""
    monkeypatch.setattr(compiled, "SMALL", 64)
    monkeypatch.setattr(compiled, "is_ready", lambda kernel: False)
    compiled.used.clear()


def test_small_inputs_on_a_cold_cache_give_the_compiled_results(monkeypatch, poses):
    r, T = poses
    r, T = r[:12], T[:12]
    table = _table()
    S = dipole.signal(r, T)
    reference = Corrector(table, "+x").batch(S)
    pose_reference = PoseCorrector(table, "+x").batch(r, rotations.from_matrix(T))
    _cold(monkeypatch)
    out = Corrector(table, "+x").batch(S)
    pose_out = PoseCorrector(table, "+x").batch(r, rotations.from_matrix(T))
    assert {compiled.name_of(correct_kernels.correct_serial), compiled.name_of(pose_kernels.invert_serial),
            compiled.name_of(lut_kernels.grid_kernel)} <= compiled.used
    for got, want in ((out, reference), (pose_out, pose_reference)):
        np.testing.assert_allclose(got.position, want.position, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got.quaternion, want.quaternion, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(got.flags, want.flags)
        np.testing.assert_array_equal(got.iterations, want.iterations)


def test_large_inputs_forced_and_ready_kernels_run_compiled(monkeypatch):
    kernel = correct_kernels.correct_serial
    monkeypatch.setattr(compiled, "SMALL", 64)
    assert compiled.choose(kernel, 65, ) is kernel
    with compiled.compiling():
        monkeypatch.setattr(compiled, "is_ready", lambda k: False)
        assert compiled.choose(kernel, 1) is kernel
    assert compiled.choose(kernel, 1) is not kernel
    monkeypatch.setattr(compiled, "SMALL", 0)  # the switch the test suite sets: always compiled
    assert compiled.choose(kernel, 1) is kernel


def test_is_ready_after_a_call():
    Corrector(_table(), "+x").batch(dipole.signal(np.array([[0.4, 0.0, 0.0]]), np.eye(3)[None]))
    assert compiled.is_ready(correct_kernels.correct_serial)


def test_the_interpreted_loop_calls_the_interpreted_model():
    """A loop made by ivc.pose.kernels.lm_driver closes over its model's kernels: its interpreted form calls
    theirs, not the dispatchers (which would compile on a cold cache)."""
    from numba.core.registry import CPUDispatcher

    from ivc.fixtures import kernels as cube_kernels
    from ivc.lut import rigid_kernels

    for solve in (correct_kernels._solve, cube_kernels._solve, rigid_kernels.solve_frame):
        loop = compiled.interpreted(solve).__globals__["_lm_solve"]
        assert not isinstance(loop, CPUDispatcher)
        hooks = [cell.cell_contents for cell in loop.__closure__]
        assert len(hooks) >= 3 and callable(hooks[0])
        assert not any(isinstance(hook, CPUDispatcher) for hook in hooks)
