"""The ambiguity test's rival search (SeedMap.rivals, compiled on a grid over the probes' images) against a
brute-force NumPy reference that tests every probe with the same criteria: on a folded room's seed map, on
queries placed at the criteria's boundaries, and on a lattice of probes whose distances tie exactly."""

from __future__ import annotations

import numpy as np
import pytest

from ivc import compiled, dipole
from ivc.correct import reported
from ivc.correct import reported_kernels as kernels
from ivc.correct.reported import REGION, RIVALS, PoseCorrector, SeedMap
from ivc.errors import InputError
from ivc.pose.tracker_solver import distortion
from ivc.table.grid import Grid
from ivc.table.lookup import LookupTable

FOLD_CENTRE = np.array([0.45, 0.0, 0.0])


def mirror_field(r):
    """tests/test_trust.py's folded room: a conductor's image source behind the volume."""
    return 0.05 * dipole.field(r - np.array([0.9, 0.0, 0.0])) @ np.diag([-1.0, 1.0, 1.0])


def reference(points, images, reach, region, v, r, tolerance, apart, limit):
    """Every probe tested: ``|φ(p) − v| − reach ≤ tolerance`` and ``|p − r| > apart``; per region the nearest in
    image (ties: the smaller probe index); the ``limit`` nearest regions (ties: the smaller region key)."""
    rows, probes = [], []
    for n in range(len(v)):
        distance = np.linalg.norm(images - v[n], axis=1)
        keep = np.flatnonzero((distance - reach <= tolerance[n])
                              & (np.linalg.norm(points - r[n], axis=1) > apart))
        taken: list[int] = []
        for p in keep[np.lexsort((keep, region[keep], distance[keep]))]:
            if len(taken) == limit:
                break
            if region[p] not in {region[q] for q in taken}:
                taken.append(int(p))
        rows += [n] * len(taken)
        probes += taken
    return np.array(rows, dtype=np.int64), np.array(probes, dtype=np.int64)


def regions(points, spacing):
    block = np.floor(points / (REGION * spacing)).astype(np.int64)
    return (block[:, 0] * 1_000_003 + block[:, 1]) * 1_000_003 + block[:, 2]


@pytest.fixture(scope="module")
def folded_seeds():
    grid = Grid(FOLD_CENTRE - 0.15, 0.03, (11, 11, 11))
    values = mirror_field(grid.nodes().reshape(-1, 3)).reshape(*grid.shape, 3, 3)
    table = LookupTable(grid, values, np.ones(grid.shape, bool), np.full(grid.shape, 100))
    return PoseCorrector(table).seeds


def boundary_queries(seeds: SeedMap, rng, n):
    """Queries whose distances sit on the criteria's boundaries: v at ``cell_reach + tolerance`` from a probe's
    image (to rounding, on either side), r at two probe spacings from another probe (likewise)."""
    p = rng.integers(0, len(seeds.probes), n)
    direction = rng.standard_normal((n, 3))
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    tolerance = rng.choice([0.0, 1e-6, 2e-4, 3e-3], n)
    nudge = rng.choice([-2, -1, 0, 1, 2], n) * 1e-16
    v = seeds.images[p] + direction * ((seeds.cell_reach[p] + tolerance) * (1 + nudge))[:, None]
    q = rng.integers(0, len(seeds.probes), n)
    away = rng.standard_normal((n, 3))
    away /= np.linalg.norm(away, axis=1)[:, None]
    r = seeds.probes[q] + away * (2 * seeds.spacing * (1 + rng.choice([-1, 0, 1], n) * 1e-16))[:, None]
    return v, r, tolerance


def assert_matches_reference(seeds: SeedMap, v, r, tolerance, limit=RIVALS):
    expected = reference(seeds.probes, seeds.images, seeds.cell_reach, regions(seeds.probes, seeds.spacing), v, r,
                         tolerance, 2 * seeds.spacing, limit)
    for serial in (False, True):
        rows, probes = seeds.rivals(v, r, tolerance, limit, serial=serial)
        np.testing.assert_array_equal(rows, expected[0])
        np.testing.assert_array_equal(probes, expected[1])
    return expected


def test_the_folded_rooms_rivals_are_the_brute_force_ones(folded_seeds):
    """Reported positions of random true positions in a room whose map folds (a fifth of its volume contested),
    solved where the map puts them, with the tolerances of the test and far wider ones (more regions tie)."""
    seeds = folded_seeds
    rng = np.random.default_rng(7)
    truth = FOLD_CENTRE + rng.uniform(-0.14, 0.14, (600, 3))
    v, _ = distortion(truth, mirror_field(truth))
    tolerance = rng.choice([1e-6, 3e-4, 3e-3, 3e-2], len(v))
    rows, _ = assert_matches_reference(seeds, v, truth, tolerance)
    assert len(np.unique(rows)) > 100 and np.bincount(rows).max() == RIVALS  # many samples, some at the limit
    assert_matches_reference(seeds, v, truth, tolerance, limit=1)
    assert_matches_reference(seeds, v, truth, tolerance, limit=0)


def test_queries_on_the_criteria_boundaries_match_the_brute_force_ones(folded_seeds):
    v, r, tolerance = boundary_queries(folded_seeds, np.random.default_rng(8), 3000)
    rows, _ = assert_matches_reference(folded_seeds, v, r, tolerance)
    assert len(rows) > 100


@pytest.mark.parametrize("layout", ["mixed", "one reach", "coarse"])
def test_exact_ties_are_broken_by_region_key_then_probe_index(layout, monkeypatch):
    """Probes on a lattice, their images on another (exact binary fractions), queries on lattice points: many
    candidates at exactly equal distances, in equal and in different regions. ``mixed``: some probes too wide to
    register; ``one reach``: every probe's the same; ``coarse``: a cap on the registrations makes the cells wider."""
    if layout == "coarse":
        monkeypatch.setattr(reported, "IMAGE_GRID_ITEMS", 3000)
    spacing = 0.25
    axis = np.arange(8) * spacing
    points = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    rng = np.random.default_rng(9)
    images = points[rng.permutation(len(points))] * 0.5  # a scrambled map: distant probes share images' distances
    reach = np.full(len(points), 0.125)
    reach[rng.random(len(points)) < 0.2] = 0.375
    reach[rng.random(len(points)) < 0.01] = 3.0  # wide: tested by every query
    if layout == "one reach":
        reach[:] = 0.375
    region = regions(points, spacing)
    grid = tuple(SeedMap._grid_over_images(images, reach))
    assert (len(grid[5]) > 0) == (layout == "mixed")  # the wide probes (coarse cells hold them all)
    assert grid[1] == np.median(reach) or layout == "coarse" and grid[1] > np.median(reach)  # the cell size
    probes = tuple(kernels.RivalProbes(points, images, reach, region))
    v = images[rng.integers(0, len(images), 400)] + rng.choice([0.0, 0.0625, -0.125], (400, 3))
    r = points[rng.integers(0, len(points), 400)]
    tolerance = rng.choice([0.0, 0.0625, 0.125], 400)
    expected = reference(points, images, reach, region, v, r, tolerance, 2 * spacing, RIVALS)
    distance = np.linalg.norm(images[expected[1]] - v[expected[0]], axis=1)
    assert np.any((expected[0][1:] == expected[0][:-1]) & (distance[1:] == distance[:-1]))  # ties were broken
    for kernel in (kernels.rivals_kernel, kernels.rivals_serial):
        found, count = np.full((400, RIVALS), -1, dtype=np.int64), np.empty(400, dtype=np.int64)
        kernel(v, r, tolerance, probes, grid, 2 * spacing, (found, count))
        np.testing.assert_array_equal(np.repeat(np.arange(400), count), expected[0])
        np.testing.assert_array_equal(found[np.arange(RIVALS) < count[:, None]], expected[1])


def test_the_interpreted_form_finds_the_same_rivals(folded_seeds):
    """What a few samples get before the kernel is compiled (ivc.compiled.interpreted): the same probes."""
    v, r, tolerance = boundary_queries(folded_seeds, np.random.default_rng(10), 40)
    compiled_rows, compiled_probes = folded_seeds.rivals(v, r, tolerance, serial=True)
    found, count = np.empty((40, RIVALS), dtype=np.int64), np.empty(40, dtype=np.int64)
    compiled.interpreted(kernels.rivals_serial)(v, r, tolerance, folded_seeds._rival_probes, folded_seeds._image_grid,
                                                2 * folded_seeds.spacing, (found, count))
    np.testing.assert_array_equal(np.repeat(np.arange(40), count), compiled_rows)
    np.testing.assert_array_equal(found[np.arange(RIVALS) < count[:, None]], compiled_probes)


def test_no_rivals_where_the_query_is_not_finite_and_a_clear_error_on_bad_shapes(folded_seeds):
    v = np.array([[np.nan, 0.0, 0.0], [0.45, 0.0, 0.0], [1e300, 0.0, 0.0]])
    rows, _ = folded_seeds.rivals(v, v, np.array([1e-3, np.nan, 1e-3]))
    assert len(rows) == 0
    with pytest.raises(InputError, match="tolerances"):
        folded_seeds.rivals(v, v, np.ones(2))
