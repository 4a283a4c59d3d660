"""Repository-wide pytest set-up: the doctest of docs/python.md runs the whole pipeline, so it is slow."""

import pytest


def pytest_collection_modifyitems(config, items):
    for item in items:
        if type(item).__name__ == "DoctestItem":
            item.add_marker(pytest.mark.slow)
