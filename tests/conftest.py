"""Shared pytest fixtures: Mitsuba variant and the shared data folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


def pytest_configure(config: pytest.Config) -> None:
    from helpers import suite_variant

    from mi_bivariate.variants import ensure_variant

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
