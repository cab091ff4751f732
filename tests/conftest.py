"""Shared test fixtures.

``shared_data``: the folder ``../shared/data`` beside the checkout. Tests that need it
skip when it is missing, unless ``MVREG_REQUIRE_SHARED=1`` (set by CI), then they fail.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def require_shared(path: Path = SHARED_DATA) -> Path:
    """``path`` if it exists; else fail (MVREG_REQUIRE_SHARED=1) or skip the test."""
    if path.exists():
        return path
    message = f"shared test data not found at {path}"
    if os.environ.get("MVREG_REQUIRE_SHARED") == "1":
        pytest.fail(message + " (MVREG_REQUIRE_SHARED=1)")
    pytest.skip(message)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ``../shared/data`` (skips or fails the test when it is missing)."""
    return require_shared()
