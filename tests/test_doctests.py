"""The examples in the exported app functions' docstrings run as written (on sample_data/, from the repository
root, as a user who cloned it would run them). Named here rather than by ``--doctest-modules`` over the package, so
that the suite collects only these examples and imports no module it does not test."""

import doctest
from pathlib import Path

import pytest

import ivc

ROOT = Path(__file__).resolve().parents[1]

#: the exported names whose docstrings hold an example
EXAMPLES = ("correct_file", "predict_file")


@pytest.mark.parametrize("name", EXAMPLES)
def test_docstring_example_runs(name, monkeypatch):
    monkeypatch.chdir(ROOT)
    function = getattr(ivc, name)
    tests = doctest.DocTestFinder(recurse=False).find(function, f"ivc.{name}", globs={})
    assert tests and tests[0].examples, f"ivc.{name} has no example"
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    for test in tests:
        runner.run(test)
    assert runner.failures == 0, f"ivc.{name}'s example failed (see the output above)"
