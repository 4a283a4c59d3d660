"""Compile the numba kernels ahead of their first use (``ivc warmup``), and where they are cached.

Every kernel is compiled lazily, on its first call, and written to numba's on-disk cache
(``cache=True``), so only the first run after an install (or an upgrade) pays for it. This
module runs each kernel a command uses once on a tiny synthetic problem, through the same
public functions (hence the same argument types) as the commands, so that the cache is
filled before a user waits on it: ``correct`` (batched and streaming correction, of signals
and of reported poses, ``ivc correct`` and ``--live``), ``fit`` (the cube solve, the harmonic
basis, the rigid-wand refinement, table evaluation: ``ivc fit``, ``ivc demo``).

The cache lives beside the sources (``__pycache__``) when the package directory is
writable, else under the user's cache directory (``ivc/__init__.py`` sets
``NUMBA_CACHE_DIR`` before numba is imported unless it is already set).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

GROUPS = ("correct", "fit")


def cache_location() -> Path:
    """Where numba writes the compiled kernels of ivc."""
    configured = os.environ.get("NUMBA_CACHE_DIR")
    if configured:
        return Path(configured)
    return Path(__file__).parent  # each subpackage's __pycache__


def _table():
    """A small table of a smooth secondary field around (0.4, 0, 0) m, every node valid."""
    from ivc.table.grid import Grid, GridField

    grid = Grid(np.array([0.3, -0.1, -0.1]), 0.05, (5, 5, 5))
    nodes = grid.nodes()
    values = 0.01 * np.einsum("...i,jk->...jk", nodes - 0.4 * np.array([1.0, 0, 0]), np.ones((3, 3)))
    return GridField(grid, values, np.ones(grid.shape, bool))


def _correct() -> None:
    from ivc import dipole
    from ivc.correct import Corrector, PoseCorrector

    corrector = Corrector(_table(), "+x", signal_noise=1e-4)  # with a noise: the precision kernels too
    r = np.array([0.4, 0.01, -0.02]) + 0.01 * np.random.default_rng(0).standard_normal((64, 3))
    q = np.tile([1.0, 0.0, 0.0, 0.0], (64, 1))
    S = dipole.signal_from_pose(r, q)
    corrector.batch(S)  # 64 frames and more: the parallel kernel
    corrector.batch(S[:4])  # fewer: the serial one
    corrector.batch_poses(r[:4], q[:4])
    corrector.update(S[:2])  # the streaming path (ivc correct --live)
    # reported poses alone (ivc correct on poses, TRANSFORM with --live)
    poses = PoseCorrector(_table(), "+x", signal_noise=1e-4)
    poses.batch(r, q)
    poses.batch(r[:4], q[:4])
    poses.warm_up(r[0])
    poses.update(r[:2], np.tile(np.eye(3), (2, 1, 1)))


def _fit() -> None:
    from ivc import dipole
    from ivc.fixtures.cube import CUBE_BITS
    from ivc.fixtures.cube_pose import solve_in_cube
    from ivc.fixtures.interpolant import HarmonicField
    from ivc.fixtures.wand import WandCalibration
    from ivc.lut import harmonics
    from ivc.lut.refine import solve_rigid

    vertices = np.array([0.38, -0.02, -0.02]) + 0.04 * CUBE_BITS
    cube = HarmonicField(vertices, np.zeros((8, 3, 3)))
    r = np.tile([0.4, 0.0, 0.0], (4, 1))
    T = np.tile(np.eye(3), (4, 1, 1))
    S = dipole.signal(r, T)
    solve_in_cube(S, cube, r[0])
    harmonics.gradient_rows(r - 0.4, 10)
    dipole.closed_form_pose(S)
    wand = WandCalibration(np.array([[0.0, 0, 0], [0, 0, 0.1]]), np.tile(np.eye(3), (2, 1, 1)), np.array([4, 4]))
    positions, rotations = wand.propagate(r, T)
    signals = np.swapaxes(rotations, -1, -2) @ dipole.field(positions)
    solve_rigid(signals, np.ones((4, 2), bool), wand, cube.value_and_jacobian, _table(), r, T)


_WARM: dict[str, Callable[[], None]] = {"correct": _correct, "fit": _fit}


def warm_up(groups: tuple[str, ...] | list[str] = GROUPS,
            progress: Callable[[str], None] | None = None) -> list[tuple[str, float]]:
    """Compile (or load from the cache) the kernels of each group; returns (group, seconds) per group.

    ``progress(group)`` is called before each group starts.
    """
    from ivc import compiled
    from ivc.errors import InputError

    unknown = [g for g in groups if g not in _WARM]
    if unknown:
        raise InputError(f"unknown warm-up group(s) {', '.join(unknown)}; use {', '.join(GROUPS)}")
    timings = []
    for group in groups:
        if progress is not None:
            progress(group)
        start = time.perf_counter()
        with compiled.compiling():  # tiny inputs, compiled kernels all the same
            _WARM[group]()
        timings.append((group, time.perf_counter() - start))
    return timings
