"""The correction map cold frames start from (ivc.correct.seed_map) and what it changes in a correction."""

from __future__ import annotations

import numpy as np

from ivc import dipole
from ivc.correct import Corrector
from ivc.correct import solver as solver_module
from ivc.correct.seed_map import correction_seeds
from ivc.dipole.pose import hemisphere_vector
from tests.helpers import distorted


def test_map_nodes_are_exact_inverses_of_the_closed_form_position(exact_table):
    field = exact_table.field()
    seeds = correction_seeds(field, hemisphere_vector("+x"))
    assert seeds.valid_cells.mean() > 0.5
    corner = np.argwhere(seeds.valid_cells)  # each valid cell's lower corner is a counted node
    v = seeds.grid.origin + seeds.grid.spacing * corner
    delta = seeds(v)  # at a node the interpolation is the node's value
    r = v + delta
    assert np.abs(delta).max() > 1e-3  # a real distortion to undo
    # independently: the NumPy closed form of f_D + g at r reproduces the node
    reported = dipole.closed_form_pose(dipole.field(r) + field(r), "+x")[0]
    np.testing.assert_allclose(reported, v, rtol=0, atol=1e-9)


def test_a_large_batch_from_the_map_gives_the_fixed_point_start_answers(exact_table, rng):
    r, T, S = distorted(rng, solver_module.SEED_MAP_FRAMES + 500)
    mapped = Corrector(exact_table).batch(S)
    fixed = Corrector(exact_table, seed_map=False).batch(S)
    np.testing.assert_array_equal(mapped.flags, fixed.flags)
    # both stop at a step below 0.1 µm: the answers agree to a few nm at worst, typically to 1e-10 m
    np.testing.assert_allclose(mapped.position, fixed.position, rtol=0, atol=1e-8)
    assert np.median(np.linalg.norm(mapped.position - fixed.position, axis=1)) < 1e-9
    np.testing.assert_allclose(mapped.position, r, rtol=0, atol=1e-8)
    assert mapped.residual.max() < 1e-8 and fixed.residual.max() < 1e-8
    assert mapped.iterations.mean() < fixed.iterations.mean()
