"""The ``Examples`` sections of the main entry points run as doctests (in the quick tier too)."""

import doctest

import pytest

import sdp.change._detect
import sdp.distance._distances
import sdp.fields._boolean
import sdp.fields._density
import sdp.io._output
import sdp.io._read
import sdp.options
import sdp.timeseries._compute

MODULES = [sdp.change._detect, sdp.fields._density, sdp.io._read, sdp.io._output, sdp.fields._boolean, sdp.options,
           sdp.distance._distances, sdp.timeseries._compute]
ENTRY_POINTS = [sdp.detect_changes, sdp.DensityField.from_points, sdp.read_points, sdp.write_points, sdp.difference,
                sdp.distances, sdp.series]


@pytest.mark.parametrize("module", MODULES, ids=lambda m: m.__name__)
def test_docstring_examples_run(module):
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.attempted > 0, f"{module.__name__} has no example"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples of {module.__name__} failed (above)"


@pytest.mark.parametrize("func", ENTRY_POINTS, ids=lambda f: f.__qualname__)
def test_entry_points_have_examples(func):
    assert "Examples\n" in func.__doc__ and ">>> " in func.__doc__
