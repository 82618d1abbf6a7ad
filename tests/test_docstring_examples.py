"""The Examples of the docstrings run and show what they print (doctest), in every module of the
library and the two jobs: an example a user copies from ``help()`` is as true as the pages'.
Illustrative lines that need the user's own data or network carry ``# doctest: +SKIP``."""

from __future__ import annotations

import doctest
import importlib
import io
import pkgutil

import pytest
import torch

PACKAGES = ("fsof_torch", "refine", "eval")


def _modules() -> list[str]:
    names = []
    for package in PACKAGES:
        root = importlib.import_module(package)
        names.append(package)
        names += [m.name for m in pkgutil.walk_packages(root.__path__, package + ".")
                  if not m.name.endswith("__main__")]
    return names


def _examples(name: str) -> list[doctest.DocTest]:
    module = importlib.import_module(name)
    return [t for t in doctest.DocTestFinder().find(module, name) if t.examples]


MODULES = [name for name in _modules() if _examples(name)]


def test_the_library_has_docstring_examples():
    assert len(MODULES) >= 10, MODULES


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name, one_thread):
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    report = io.StringIO()
    with torch.random.fork_rng():
        torch.manual_seed(0)
        for test in _examples(name):
            runner.run(test, out=report.write)
    failed, attempted = runner.summarize(verbose=False)
    assert failed == 0, f"{name}: {failed} of {attempted} docstring example(s) failed:\n{report.getvalue()}"
