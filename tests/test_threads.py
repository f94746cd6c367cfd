"""mi_bivariate.threads: BLAS pools pinned inside the block and restored after it."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from mi_bivariate import process, threads


def _blas_threads() -> list:
    np.dot(np.ones((2, 2)), np.ones((2, 2)))  # make sure the BLAS is loaded
    importlib.import_module("scipy.linalg")  # and scipy's own (the one the solve's LAPACK calls use)
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def test_blas_threads_limits_and_restores(monkeypatch):
    monkeypatch.delenv(process.BLAS_THREADS_ENV_VAR, raising=False)
    before = _blas_threads()
    assert before
    with threads.blas_threads():
        assert _blas_threads() == [process.DEFAULT_BLAS_THREADS] * len(before)
        with threads.blas_threads(None):  # "leave alone" inside a limit keeps the limit
            assert _blas_threads() == [process.DEFAULT_BLAS_THREADS] * len(before)
    assert _blas_threads() == before


def test_environment_variable(monkeypatch):
    monkeypatch.setenv(process.BLAS_THREADS_ENV_VAR, "2")
    assert process.configured_blas_threads() == 2
    monkeypatch.setenv(process.BLAS_THREADS_ENV_VAR, "default")
    assert process.configured_blas_threads() is None
    before = _blas_threads()
    with threads.blas_threads():
        assert _blas_threads() == before
    monkeypatch.setenv(process.BLAS_THREADS_ENV_VAR, "nonsense")
    assert process.configured_blas_threads() == process.DEFAULT_BLAS_THREADS


def test_thread_map_runs_items_at_once():
    """Two items that each wait for the other finish only if they run concurrently."""
    import threading

    barrier = threading.Barrier(2, timeout=10)
    assert threads.thread_map(lambda i: (barrier.wait(), i)[1], range(2), 2) == [0, 1]


def test_thread_map_keeps_order_and_raises(monkeypatch):
    import time

    def slow_square(i):
        time.sleep(0.01 * (3 - i))  # later items finish first
        return i * i

    for n in (1, 2, 3, 8):
        assert threads.thread_map(slow_square, range(4), n) == [0, 1, 4, 9]

    def boom(i):
        if i == 2:
            raise ValueError("item 2")
        return i

    with pytest.raises(ValueError, match="item 2"):
        threads.thread_map(boom, range(4), 2)
    monkeypatch.setenv(threads.SOLVE_ENV_VAR, "1")
    assert threads.solve_threads() == 1
    monkeypatch.setenv(threads.SOLVE_ENV_VAR, "5")
    assert threads.solve_threads() == 5
    for text in ("", "0", "nonsense", "-2"):
        monkeypatch.setenv(threads.SOLVE_ENV_VAR, text)
        assert 1 <= threads.solve_threads() <= threads.MAX_SOLVE_THREADS


def test_solve_threads_share_the_cores_with_blas(monkeypatch):
    """With multi-threaded BLAS, workers times BLAS threads never exceed the cores (oversubscription
    made the solve 3x slower); with one BLAS thread each, one worker per channel on 2+ cores."""
    import os

    monkeypatch.delenv(threads.SOLVE_ENV_VAR, raising=False)
    cores = len(os.sched_getaffinity(0))
    with threads.blas_threads(1):
        assert threads.solve_threads() == (threads.MAX_SOLVE_THREADS if cores >= 2 else 1)
    with threads.blas_threads(cores):
        assert threads.solve_threads() == 1
    for fake_cores, blas, expected in ((4, 2, 2), (3, 2, 1), (6, 3, 2), (8, 4, 2), (1, 1, 1), (2, 1, 3), (16, 2, 3)):
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid, n=fake_cores: set(range(n)))
        with threads.blas_threads(blas):
            got = threads.solve_threads()
        assert got == expected, (fake_cores, blas, got)
        assert blas == 1 or got * blas <= fake_cores


def test_solve_thread_limit_caps_and_restores(monkeypatch):
    monkeypatch.setenv(threads.SOLVE_ENV_VAR, "3")
    with threads.solve_thread_limit(1):
        assert threads.solve_threads() == 1
        with threads.solve_thread_limit(None):  # no change inside a limit
            assert threads.solve_threads() == 1
        with threads.solve_thread_limit(5):  # nested: the smaller limit holds
            assert threads.solve_threads() == 1
    with threads.solve_thread_limit(5):  # a cap, never a raise
        assert threads.solve_threads() == 3
    assert threads.solve_threads() == 3
