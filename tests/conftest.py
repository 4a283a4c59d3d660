import numpy as np
import pytest

from ivc.lut import Grid, LookupTable
from tests.helpers import CENTRE, quadratic_field


@pytest.fixture
def rng():
    return np.random.default_rng(20261121)


@pytest.fixture(scope="session")
def small_session():
    """A quick simulated protocol (short sweep, few check poses) next to one aluminium plate."""
    from ivc.sim import Simulator
    from ivc.sim.scene import scene_from_dict

    scene = scene_from_dict({"conductor": [{"shape": "plate", "size": [1.0, 1.0], "position": [0.5, 0, -0.35],
                                            "material": "aluminium", "resolution_mm": 80}]})
    scene.tabulate = False
    simulator = Simulator(scene, seed=9)
    session = simulator.protocol({"cube_calibration": 1000, "cube_survey": 200, "wand_calibration": 200,
                                  "wand_sweep": 3000, "check": 300})
    return simulator, session


@pytest.fixture(scope="session")
def exact_table():
    """A table holding a field exactly quadratic in r, which cubic interpolation reproduces exactly."""
    grid = Grid(CENTRE - 0.25, 0.025, (21, 21, 21))
    values = quadratic_field(grid.nodes().reshape(-1, 3)).reshape(*grid.shape, 3, 3)
    return LookupTable(grid, values, np.ones(grid.shape, bool), np.full(grid.shape, 100))
