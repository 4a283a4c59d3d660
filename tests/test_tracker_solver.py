"""The tracker model: reported pose from true pose and secondary field, both solvers, with Jacobians."""

import numpy as np
import pytest

from ivc import dipole, rotations
from ivc.errors import InputError, SceneError
from ivc.pose import tracker_solver as ts
from ivc.sim import Simulator
from ivc.sim.field import FerrousSphere
from ivc.sim.scene import NoiseSpec, Scene, scene_from_dict

SPHERE = FerrousSphere(np.array([0.62, 0.1, -0.12]), 0.05, 1000.0)


def sphere_field(r):
    """A ferrous sphere's secondary field and its exact Jacobian (1/m⁴)."""
    k = SPHERE.radius**3 * (SPHERE.permeability - 1) / (SPHERE.permeability + 2)
    g = SPHERE.field(r)
    dg = k * np.einsum("...ilk,lj->...ijk", dipole.field_jacobian(r - SPHERE.position), dipole.field(SPHERE.position))
    return g, dg


def poses(n=6, seed=1):
    rng = np.random.default_rng(seed)
    r = np.array([0.5, 0.0, 0.0]) + 0.08 * rng.standard_normal((n, 3))
    T = rotations.to_matrix(rotations.random(n, rng))
    return r, T


@pytest.mark.parametrize("solver", ts.SOLVERS)
def test_reported_position_does_not_depend_on_orientation_and_turn_is_a_rotation(solver):
    r, _ = poses()
    g, _ = sphere_field(r)
    F = dipole.field(r) + g
    phi, C = ts.distortion(r, g, solver=solver)
    assert np.all(np.linalg.norm(phi - r, axis=1) > 1e-4)  # the field really distorts
    np.testing.assert_allclose(C @ np.swapaxes(C, -1, -2), np.broadcast_to(np.eye(3), C.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(C), 1.0, atol=1e-12)
    for seed in range(3):
        T = rotations.to_matrix(rotations.random(len(r), seed))
        position, rotation = ts.reported_pose(np.swapaxes(T, -1, -2) @ F, solver)
        np.testing.assert_allclose(position, phi, atol=1e-12)
        np.testing.assert_allclose(rotation, C @ T, atol=1e-11)


def test_free_space_is_reported_exactly_by_both_solvers():
    r, T = poses()
    for solver in ts.SOLVERS:
        position, rotation = ts.reported_pose(dipole.signal(r, T), solver)
        np.testing.assert_allclose(position, r, atol=1e-12)
        np.testing.assert_allclose(rotation, T, atol=1e-10)


def test_least_squares_minimises_the_signal_residual_better_than_the_closed_form():
    r, T = poses()
    g, _ = sphere_field(r)
    S = np.swapaxes(T, -1, -2) @ (dipole.field(r) + g)

    def cost(position, rotation):
        return np.linalg.norm(S - np.swapaxes(rotation, -1, -2) @ dipole.field(position), axis=(1, 2))

    ls, cf = ts.reported_pose(S, "least-squares"), ts.reported_pose(S, "closed-form")
    assert np.all(cost(*ls) < cost(*cf))
    assert np.all(np.linalg.norm(ls[0] - cf[0], axis=1) > 1e-8)  # the two solvers really differ here
    assert np.max(np.linalg.norm(ls[0] - cf[0], axis=1)) > 1e-6


@pytest.mark.parametrize("solver", ts.SOLVERS)
def test_signal_jacobian_matches_finite_differences(solver):
    r, T = poses(4)
    g, _ = sphere_field(r)
    S = np.swapaxes(T, -1, -2) @ (dipole.field(r) + g)
    _, _, J = ts.reported_pose_jacobian(S, solver)
    h = 1e-6 * np.abs(S).max()
    numeric = np.zeros_like(J)
    for d in range(9):
        dS = np.zeros(9)
        dS[d] = h
        dS = dS.reshape(3, 3)
        p1, R1 = ts.reported_pose(S + dS, solver)
        p0, R0 = ts.reported_pose(S - dS, solver)
        numeric[:, :3, d] = (p1 - p0) / (2 * h)
        numeric[:, 3:, d] = ts.left_difference(R1, R0) / (2 * h)
    np.testing.assert_allclose(J, numeric, rtol=0, atol=1e-6 * np.abs(J).max())


@pytest.mark.parametrize("solver", ts.SOLVERS)
def test_position_jacobian_of_the_distortion_matches_finite_differences(solver):
    r, _ = poses(4, seed=3)
    g, dg = sphere_field(r)
    phi, C, dphi, domega, _ = ts.distortion(r, g, dg, solver=solver, jacobian=True)
    h = 1e-7
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        p1, C1 = ts.distortion(r + step, sphere_field(r + step)[0], solver=solver)
        p0, C0 = ts.distortion(r - step, sphere_field(r - step)[0], solver=solver)
        np.testing.assert_allclose(dphi[..., k], (p1 - p0) / (2 * h), atol=1e-6)
        np.testing.assert_allclose(domega[..., k], ts.left_difference(C1, C0) / (2 * h), atol=1e-5)


def test_field_hessian_matches_the_jacobian_by_finite_differences():
    r, _ = poses(3)
    h = 1e-7
    H = ts.field_hessian(r)
    for k in range(3):
        step = np.zeros(3)
        step[k] = h
        numeric = (dipole.field_jacobian(r + step) - dipole.field_jacobian(r - step)) / (2 * h)
        np.testing.assert_allclose(H[..., k], numeric, rtol=1e-6, atol=1e-6 * np.abs(H).max())


def test_non_finite_signals_give_nan_and_unknown_solvers_are_refused():
    S = np.full((2, 3, 3), np.nan)
    S[1] = dipole.field([0.5, 0.0, 0.0])
    for solver in ts.SOLVERS:
        position, _ = ts.reported_pose(S, solver)
        assert np.isnan(position[0]).all() and np.isfinite(position[1]).all()
    with pytest.raises(InputError, match="least-squares"):
        ts.reported_pose(S, "kalman")


def test_the_simulator_reports_with_the_scene_s_tracker_solver():
    with pytest.raises(SceneError, match="tracker"):
        scene_from_dict({"tracker": "magic"})
    scene = Scene(spheres=[SPHERE], noise=NoiseSpec.none(), solver="least-squares")
    assert scene_from_dict({"solver": "least-squares"}).solver == "least-squares"
    assert scene_from_dict({"tracker": "least-squares"}).solver == "least-squares"  # the key's old name
    step, truth = Simulator(scene, 0).step("check", 50)
    S = step.signal
    position, rotation = ts.reported_pose(S, "least-squares")
    np.testing.assert_allclose(step.position, position, atol=1e-12)
    np.testing.assert_allclose(rotations.to_matrix(step.quaternion), rotation, atol=1e-9)
    closed, _ = ts.reported_pose(S, "closed-form")
    assert np.max(np.linalg.norm(closed - position, axis=-1)) > 1e-6
    assert step.attrs["tracker_solver"] == "least-squares"
    with pytest.raises(SceneError, match="once"):
        scene_from_dict({"solver": "least-squares", "tracker": "closed-form"})
    # the simulated device on its own records what the simulator records with it (no noise: the rng draws nothing
    # that matters)
    simulator = Simulator(scene, 0)
    device = simulator.device
    assert (device.solver, device.rate_hz, device.model) == ("least-squares", scene.sweep_rate_hz, None)
    again = device.measure(truth.position, truth.quaternion, secondary=simulator.secondary,
                           rng=np.random.default_rng(1), description=step.description, sensor_prefix="check")
    np.testing.assert_array_equal(again.signal, step.signal)
    np.testing.assert_array_equal(again.position, step.position)
