"""The shared recordings for tests: ``../shared/data`` beside the checkout (read in place, never
copied into the repository; /work/shared/data/README.md describes them)."""
from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def require_shared(path: Path) -> Path:
    """``path`` (a file or folder of the shared data), or skip the calling test when it is absent."""
    if not path.exists():
        pytest.skip(f"shared data not found: {path} (see ../shared/data/README.md)")
    return path


def needs_shared(path: Path) -> pytest.MarkDecorator:
    """A skip mark for a test (or ``pytestmark``) that needs ``path`` of the shared data."""
    return pytest.mark.skipif(not path.exists(), reason=f"shared data not found: {path}")
