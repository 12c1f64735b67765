"""Shared test fixtures. The ``slow`` marker (multi-process, long-running) is registered in
pyproject.toml: ``make test-fast`` runs ``-m "not slow"``, ``make test`` everything."""
from __future__ import annotations

from pathlib import Path

import pytest

from tests.shared_data import SHARED_DATA, require_shared


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The shared recordings folder (``../shared/data``); the test is skipped when it is absent."""
    return require_shared(SHARED_DATA)
