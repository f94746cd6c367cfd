"""mi_bivariate.threads: BLAS pools pinned inside the block and restored after it."""

from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_info

from mi_bivariate import threads


def _blas_threads() -> list:
    np.dot(np.ones((2, 2)), np.ones((2, 2)))  # make sure the BLAS is loaded
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def test_blas_threads_limits_and_restores(monkeypatch):
    monkeypatch.delenv(threads.ENV_VAR, raising=False)
    before = _blas_threads()
    assert before
    with threads.blas_threads():
        assert _blas_threads() == [threads.DEFAULT_BLAS_THREADS] * len(before)
        with threads.blas_threads(None):  # "leave alone" inside a limit keeps the limit
            assert _blas_threads() == [threads.DEFAULT_BLAS_THREADS] * len(before)
    assert _blas_threads() == before


def test_environment_variable(monkeypatch):
    monkeypatch.setenv(threads.ENV_VAR, "2")
    assert threads.configured_threads() == 2
    monkeypatch.setenv(threads.ENV_VAR, "default")
    assert threads.configured_threads() is None
    before = _blas_threads()
    with threads.blas_threads():
        assert _blas_threads() == before
    monkeypatch.setenv(threads.ENV_VAR, "nonsense")
    assert threads.configured_threads() == threads.DEFAULT_BLAS_THREADS
