"""The examples in the docstrings of the names ``import ivc`` exports run as doctests (the API reference of the
documentation site shows them)."""

import doctest

import pytest

import ivc


def _exported_with_examples():
    finder = doctest.DocTestFinder(exclude_empty=True)
    for name, (_, attribute) in sorted(ivc._EXPORTS.items()):
        if attribute is None:
            continue
        for test in finder.find(getattr(ivc, name), f"ivc.{name}"):
            if test.examples:
                yield pytest.param(test, id=test.name)


EXAMPLES = list(_exported_with_examples())


@pytest.mark.parametrize("test", EXAMPLES)
def test_docstring_example(test, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # examples that write files write them here
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{test.name}: {result.failed} of {result.attempted} examples failed"
