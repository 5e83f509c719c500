"""The Examples sections of the main entry points run as doctests (they are documentation
that must stay true)."""

from __future__ import annotations

import doctest
import importlib

import pytest

MODULES = [
    "pipeline.core.validate",
    "pipeline.core.psf",
    "pipeline.core.deconvolve.dispatch",
    "pipeline.core.simulate.render",
    "pipeline.jobs.stack",
]


@pytest.mark.parametrize("name", MODULES)
def test_examples_run(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0, f"{name} has no examples"
    assert result.failed == 0
