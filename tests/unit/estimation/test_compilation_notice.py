"""The one line that says kernels are being compiled: on a real compilation only, once per process."""

from __future__ import annotations

import importlib.util
import logging
import sys

import numpy as np
import pytest
from numba import njit

from kalmansfm import _compilation

KERNEL = '''
from numba import njit


@njit(cache=True)
def total(a):
    s = 0.0
    for v in a:
        s += v
    return s
'''


@pytest.fixture
def fresh(monkeypatch, caplog):
    """A process-like state where nothing has been announced yet; INFO lines of 'kalmansfm' captured."""
    monkeypatch.setitem(_compilation._state, "announced", False)
    _compilation.watch_compilation()
    caplog.set_level(logging.INFO, logger="kalmansfm")
    return caplog


def _kernel(module: str):
    def add_one(a):
        return a + 1.0
    add_one.__module__ = module
    return njit(add_one)


def _notices(caplog) -> int:
    return sum(r.getMessage() == _compilation.MESSAGE for r in caplog.records)


def test_the_first_compilation_of_a_kalmansfm_kernel_is_announced_once(fresh):
    _kernel("kalmansfm.probe")(np.ones(2))
    _kernel("kalmansfm.probe")(np.ones(3))  # another compilation, same process: no second line
    assert _notices(fresh) == 1


def test_other_libraries_compilations_are_not_announced(fresh):
    _kernel("someone_else")(np.ones(2))
    assert _notices(fresh) == 0


def _load(path, name):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_kernel_loaded_from_the_cache_is_not_announced(fresh, tmp_path, monkeypatch):
    path = tmp_path / "probe_kernel.py"
    path.write_text(KERNEL)
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    first = _load(path, "kalmansfm._probe_cached")
    assert first.total(np.ones(4)) == 4.0  # compiled and written to the cache
    assert _notices(fresh) == 1
    fresh.clear()
    _compilation._state["announced"] = False
    second = _load(path, "kalmansfm._probe_cached_again")  # a new dispatcher: as a new process would
    assert second.total(np.ones(5)) == 5.0
    assert second.total.stats.cache_hits  # it was loaded, not compiled
    assert _notices(fresh) == 0
