import numpy as np
import pytest


@pytest.fixture
def rng():
    return np.random.default_rng(20261121)


def random_positions(rng, n, low=0.05, high=2.0, hemisphere=None):
    """Random positions with range uniform in [low, high] metres, directions uniform."""
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if hemisphere is not None:
        d *= np.where(d @ hemisphere < 0, -1.0, 1.0)[:, None]
    return d * rng.uniform(low, high, (n, 1))


@pytest.fixture(scope="session")
def small_session():
    """A quick simulated protocol (short sweep, few check poses) next to one aluminium plate."""
    from ivc.session import Session
    from ivc.sim import Simulator
    from ivc.sim.scene import scene_from_dict

    scene = scene_from_dict({"conductor": [{"shape": "plate", "size": [1.0, 1.0], "position": [0.5, 0, -0.35],
                                            "material": "aluminium", "resolution_mm": 80}]})
    scene.tabulate = False
    simulator = Simulator(scene, seed=9)
    session = Session()
    for name, frames in (("cube_calibration", 1000), ("cube_survey", 200), ("wand_calibration", 200),
                         ("wand_sweep", 3000), ("check", 300)):
        session.steps[name], session.truth[name] = simulator.step(name, frames)
    return simulator, session
