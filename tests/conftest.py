"""Shared pytest fixtures: Mitsuba variant and the shared data folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


def pytest_configure(config: pytest.Config) -> None:
    from helpers import suite_variant

    from mi_bivariate import process
    from mi_bivariate.variants import ensure_variant

    # As the command line does in its own process: on this project's VM transparent huge pages cost
    # seconds of system time in a run of recoveries (tests/test_recover.py: 94 -> 85 s, system time
    # 20.6 -> 11.9 s). Only the speed changes; the processes the tests start inherit it, and the tests
    # of that setting turn huge pages back on in their child first (tests/test_package.py).
    process.no_huge_pages()
    ensure_variant(suite_variant())


def _data_dir() -> Path | None:
    value = os.environ.get("MI_BIVARIATE_DATA")
    if not value:
        return None
    path = Path(value)
    return path if path.is_dir() else None


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared data folder; tests using it are skipped when it is absent."""
    path = _data_dir()
    if path is None:
        pytest.skip("shared data not available: set MI_BIVARIATE_DATA to the shared data folder")
    return path


@pytest.fixture(scope="session")
def probe_path(data_dir: Path):
    def _probe_path(name: str) -> Path:
        matches = sorted((data_dir / "probes").glob(f"{name}.*"))
        if not matches:
            pytest.skip(f"shared probe {name!r} not found in {data_dir / 'probes'}")
        return matches[0]

    return _probe_path


@pytest.fixture(scope="session")
def loo_reductions() -> None:
    """The shared MERL-NBRDF materials reduced on the 32 x 32 grid, in the reductions cache
    (:func:`mi_bivariate.training_set.reduced_tables`, ``~/.cache/mi_bivariate``), before the tests whose
    run learns leave-one-out priors from them (``demo``, the quickstart notebook). With a cold cache this is
    the 73 materials' network evaluations (~2.5 s each on 2 cores, several minutes under load): made here
    once, outside the notebook's per-cell time limit, which it used to exceed (and then the next test made
    them again). Nothing without the shared data (those runs use the packaged priors)."""
    from mi_bivariate import training_set
    from mi_bivariate.sources import have_shared_data

    if have_shared_data():
        training_set.reduced_tables(32, 32)
