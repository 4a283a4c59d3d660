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
