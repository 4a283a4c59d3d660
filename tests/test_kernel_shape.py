"""The compiled layer's shape (docs/kernels.md, "Bundles instead of long argument lists"): no compiled function
takes more than 12 arguments, what was positional is a named bundle (no workspace read as ``ws[0]`` … ``ws[32]``),
and the threaded and serial kernels of one loop body agree to the bit."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

import ivc

PACKAGE = Path(ivc.__file__).parent
MAX_ARGUMENTS = 12
#: compiled functions still taking more than MAX_ARGUMENTS arguments (module path: names), each to be bundled
NOT_YET_BUNDLED: dict[str, set[str]] = {}
#: names a scratch bundle goes by in the kernels: read by field name, never by position
WORKSPACE_NAMES = {"ws", "work", "lm", "workspace"}


def _compiled(node: ast.FunctionDef) -> bool:
    return any("jit" in ast.unparse(d) for d in node.decorator_list)


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        yield path.relative_to(PACKAGE).as_posix(), ast.parse(path.read_text(encoding="utf-8"))


def test_no_compiled_function_takes_more_than_twelve_arguments():
    long = {}
    for name, tree in _modules():
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef) and _compiled(node):
                count = len(node.args.posonlyargs) + len(node.args.args) + len(node.args.kwonlyargs)
                if count > MAX_ARGUMENTS and node.name not in NOT_YET_BUNDLED.get(name, ()):
                    long[f"{name}:{node.name}"] = count
    assert not long, f"compiled functions with more than {MAX_ARGUMENTS} arguments (pass a named bundle): {long}"


def test_the_exceptions_are_still_there():
    """An exception that no longer exists (renamed or bundled) leaves the list."""
    present = {name: {node.name for node in ast.walk(tree) if isinstance(node, ast.FunctionDef) and _compiled(node)
                      and len(node.args.args) > MAX_ARGUMENTS}
               for name, tree in _modules()}
    stale = {name: names - present.get(name, set()) for name, names in NOT_YET_BUNDLED.items()}
    assert not any(stale.values()), f"listed as unbundled but not found: {stale}"


def test_no_workspace_is_read_by_position():
    positional = []
    for name, tree in _modules():
        for node in ast.walk(tree):
            if (isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name)
                    and node.value.id in WORKSPACE_NAMES and isinstance(node.slice, ast.Constant)):
                positional.append(f"{name}:{node.lineno} {ast.unparse(node)}")
    assert not positional, f"a workspace read by position (name its fields): {positional}"


def _table():
    from ivc.table.grid import Grid, GridField

    grid = Grid(np.array([0.3, -0.1, -0.1]), 0.05, (5, 5, 5))
    x = grid.nodes() - np.array([0.4, 0.0, 0.0])
    values = 0.01 * (x[..., 0, None, None] * np.eye(3) + x[..., 1, None, None] * np.ones((3, 3)))
    return GridField(grid, values, np.ones(grid.shape, bool))


@pytest.mark.parametrize("use_map", [False, True])
def test_the_threaded_and_serial_correction_agree_to_the_bit(rng, use_map):
    from ivc import dipole, rotations
    from ivc.correct import kernels
    from ivc.correct.seed_map import correction_seeds

    field = _table()
    n = 300  # more than one block of the threaded kernel
    r = np.array([0.4, 0.0, 0.0]) + 0.02 * rng.standard_normal((n, 3))
    T = rotations.to_matrix(rotations.random(n, rng))
    S = dipole.signal(r, T) + 1e-4 * rng.standard_normal((n, 3, 3))
    seeds = np.full((n, 3), np.nan)
    seeds[::7] = r[::7]  # some warm starts
    h = dipole.hemisphere_vector("+x")
    seed_map = correction_seeds(field, h).kernel_grid if use_map else field.kernel_grid
    config = kernels.Config(use_map, 60, 1e-7, 2e-3)  # retried above a 0.2 % residual: the retries run too
    outputs = []
    for kernel in (kernels.correct_kernel, kernels.correct_serial):
        out = kernels.Output(np.full((n, 3), -1.0), np.full((n, 3, 3), -1.0), np.full((n, 4), -1.0),
                             np.zeros(n, bool), np.full(n, -1, np.int64), np.full(n, -1.0), np.zeros(n, bool))
        kernel(S, seeds, h, field.kernel_grid, seed_map, tuple(config), tuple(out))  # as the Corrector passes them
        outputs.append(out)
    threaded, serial = outputs
    assert threaded.converged.mean() > 0.9 and np.all(threaded.iterations >= 0)  # every row written
    for name in kernels.Output._fields:
        assert np.array_equal(getattr(threaded, name), getattr(serial, name), equal_nan=True), name
