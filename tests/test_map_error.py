"""The map's own error from the residuals revisits share (ivc.lut.map_error), and its place in the precision."""

from __future__ import annotations

import numpy as np
import pytest

from ivc import rotations
from ivc.correct import PoseCorrector
from ivc.errors import InputError
from ivc.lut.map_error import shared_residual
from ivc.lut.reported_build import DISAGREEMENT, table_error
from ivc.pose.precision import reported_noise
from ivc.pose.reported_fit import PosePairs
from ivc.pose.tracker_solver import distortion
from ivc.table.grid import Grid
from ivc.table.lookup import LookupTable
from tests.helpers import CENTRE, quadratic_field

GRID = Grid(CENTRE - 0.25, 0.025, (21, 21, 21))


def visits(rng, n=60_000, seconds=600.0, radius=0.1):
    """Positions (n, 3) m in a ball about the centre, each at a random time in ``seconds`` (revisits)."""
    direction = rng.standard_normal((n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    r = CENTRE + radius * np.cbrt(rng.random(n))[:, None] * direction
    return r, np.sort(rng.random(n) * seconds)


def cell_of(r):
    cell = np.floor((r - GRID.origin) / GRID.spacing).astype(int)
    return np.ravel_multi_index(cell.T, GRID.shape)


def test_the_error_revisits_share_is_found_under_noise_ten_times_larger(rng):
    r, t = visits(rng)
    per_cell = 0.03 * rng.standard_normal((int(np.prod(GRID.shape)), 3)) / np.sqrt(3)
    shared = per_cell[cell_of(r)]
    noise = 0.3 * rng.standard_normal(r.shape) / np.sqrt(3)
    truth = np.sqrt(np.mean(np.sum(shared**2, axis=1)))
    assert shared_residual(r, shared + noise, t, GRID) == pytest.approx(truth, rel=0.15)
    assert shared_residual(r, noise, t, GRID) < 0.1 * truth  # noise alone: next to nothing


def test_an_error_that_only_consecutive_samples_share_is_not_the_maps(rng):
    r, t = visits(rng)
    block = np.floor(t / 10.0).astype(int)
    slow = 0.05 * rng.standard_normal((block.max() + 1, 3))[block]  # e.g. the fixture's pose error, block by block
    assert shared_residual(r, slow, t, GRID) < 0.01
    # an error of the same size that belongs to the place: found
    placed = 0.05 * rng.standard_normal((int(np.prod(GRID.shape)), 3))[cell_of(r)]
    assert shared_residual(r, placed, t, GRID) == pytest.approx(0.05 * np.sqrt(3), rel=0.15)


def test_shapes_are_checked(rng):
    r, t = visits(rng, 10)
    with pytest.raises(InputError, match="must be"):
        shared_residual(r, np.zeros(10), t, GRID)
    with pytest.raises(InputError, match="block_seconds"):
        shared_residual(r, np.zeros((10, 3)), t, GRID, block_seconds=0)
    assert np.isnan(shared_residual(r[:1], np.zeros((1, 3)), t[:1], GRID))


def perturbed_table(amplitude):
    """The exact quadratic table with a smooth error of ``amplitude`` (field units) added."""
    nodes = GRID.nodes().reshape(-1, 3)
    error = amplitude * np.sin(40 * (nodes - CENTRE))[:, :, None] * np.array([1.0, -0.5, 0.7])
    values = (quadratic_field(nodes) + error).reshape(*GRID.shape, 3, 3)
    return LookupTable(GRID, values, np.ones(GRID.shape, bool), np.full(GRID.shape, 100))


def test_the_table_error_of_a_known_wrong_map_is_its_reported_pose_error(rng):
    """Pairs recorded in the true (quadratic) field with 0.2 mm / 2 mrad tracker noise, judged against a table
    that is wrong by a known smooth error: the estimate is the RMS reported-pose error the wrong map makes."""
    r, t = visits(rng, 80_000)
    T = rotations.to_matrix(rotations.random(len(r), rng))
    v, C = distortion(r, quadratic_field(r))
    table = perturbed_table(2e-3)
    v_table, C_table = distortion(r, table.field().evaluate(r)[0].reshape(-1, 3, 3))
    position_truth = np.sqrt(np.mean(np.sum((v_table - v) ** 2, axis=1)))
    turn = rotations.to_rotvec(rotations.from_matrix(C_table @ np.swapaxes(C, -1, -2)))
    orientation_truth = np.sqrt(np.mean(np.sum(turn**2, axis=1)))
    assert 2e-5 < position_truth < 2e-4  # a map error well under the noise
    noise = rotations.to_matrix(rotations.from_rotvec(2e-3 / np.sqrt(3) * rng.standard_normal(r.shape)))
    pairs = PosePairs(r, T, v + 2e-4 / np.sqrt(3) * rng.standard_normal(r.shape), noise @ C @ T,
                      np.arange(len(r)), np.ones(len(r), int))
    found = table_error(pairs, table.field(), t, "closed-form", "+x")
    assert 1e-3 * found["position_mm"] == pytest.approx(position_truth, rel=0.15)
    assert 1e-3 * found["orientation_mrad"] == pytest.approx(orientation_truth, rel=0.2)
    exact = table_error(pairs, perturbed_table(0.0).field(), t, "closed-form", "+x")
    assert exact["position_mm"] < 0.15 * found["position_mm"]


def test_the_map_error_adds_to_the_predicted_precision_in_quadrature(exact_table, rng):
    fit = {"map_error": {"position_mm": 0.05, "orientation_mrad": 0.2}, "signal_noise": {"sigma": 1e-4}}
    table = LookupTable(exact_table.grid, exact_table.values, exact_table.valid, exact_table.support, fit=fit)
    assert table.map_error == pytest.approx((5e-5, 2e-4))
    r, _ = visits(rng, 200, radius=0.12)
    v, C = distortion(r, quadratic_field(r))
    q = rotations.from_matrix(C)
    with_error = PoseCorrector(table, max_precision=None).batch(v, q)
    without = PoseCorrector(table, max_precision=None, table_error=False).batch(v, q)
    np.testing.assert_allclose(with_error.precision ** 2, without.precision ** 2 + 5e-5 ** 2, rtol=1e-12)
    np.testing.assert_allclose(with_error.orientation_precision ** 2, without.orientation_precision ** 2 + 2e-4 ** 2,
                               rtol=1e-12)
    np.testing.assert_array_equal(with_error.position, without.position)
    streamed = PoseCorrector(table, max_precision=None)
    one = streamed.update(v[:1], C[:1])
    assert one.precision[0] == pytest.approx(with_error.precision[0], rel=1e-6)


def test_samples_that_disagree_with_the_map_beyond_the_noise_make_its_error_their_spread(rng):
    """Samples whose reported positions scatter as the tracker's noise: no excess. Samples that are off by 20x
    that noise, each its own way (no revisit shares it): the map error is their RMS beyond 5x the noise."""
    r, t = visits(rng, 20_000)
    T = rotations.to_matrix(rotations.random(len(r), rng))
    v, C = distortion(r, quadratic_field(r))
    sigma = 1e-3
    noise = reported_noise(v, C @ T, sigma)
    table = perturbed_table(0.0)

    def pairs_with(spread):
        off = spread[:, None] * rng.standard_normal(r.shape) / np.sqrt(3)
        return PosePairs(r, T, v + off, C @ T, np.arange(len(r)), np.ones(len(r), int))

    quiet = table_error(pairs_with(noise), table.field(), t, "closed-form", "+x", sigma)
    assert quiet["disagreement"] < 1.2 and quiet["excess_position_mm"] == 0
    loud_pairs = pairs_with(20 * noise)
    loud = table_error(loud_pairs, table.field(), t, "closed-form", "+x", sigma)
    length2 = np.sum((loud_pairs.reported_position - v) ** 2, axis=1)
    expected = np.sqrt(np.mean(length2) - DISAGREEMENT**2 * np.mean(noise**2))
    assert loud["disagreement"] > 15
    assert 1e-3 * loud["position_mm"] == pytest.approx(expected, rel=0.02)
    assert loud["shared_position_mm"] < 0.2 * loud["position_mm"]  # no revisit shares it


@pytest.mark.slow
def test_the_pose_only_demo_corrects_with_the_tables_trust_test():
    """`ivc demo --pose-only` evaluated its check poses with a corrector built from the table's field alone: no
    signal noise, so no predicted precision, no map error and no precision gate. Now the table's own."""
    from ivc import demo as ivc_demo

    result = ivc_demo.run(sweep_frames=3000, check_frames=300, pose_only=True)
    error = result.table.map_error
    assert error is not None and 0 < error[0] < 1e-3
    assert result.table.fit["map_error"]["disagreement"] < 5
    report = result.report
    assert report["input"] == "reported poses"
    assert 0.3 < report["predicted_precision"]["error_over_predicted_median"] < 3
