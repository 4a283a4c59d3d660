"""Repository-wide pytest set-up: the doctest of docs/python.md runs the whole pipeline, so it is slow."""

import os

import pytest

# the tests exercise the compiled kernels, whatever the state of the cache: no interpreted stand-ins for small
# inputs (ivc.compiled; tests/test_compiled.py tests those on purpose). Subprocesses inherit it.
os.environ.setdefault("IVC_INTERPRETED_MAX", "0")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if type(item).__name__ == "DoctestItem":
            item.add_marker(pytest.mark.slow)
