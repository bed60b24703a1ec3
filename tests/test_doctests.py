"""The runnable examples in the docstrings are part of the documentation: they must run."""

import doctest
import importlib
import pkgutil

import pytest

import torchevtrack

MODULES = sorted(m.name for m in pkgutil.walk_packages(torchevtrack.__path__, "torchevtrack.")
                 if not m.name.endswith("__main__"))


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.failed == 0
