"""Shared test fixtures.

``shared_data``: the folder ``../shared/data`` beside the checkout. Tests that need it
skip when it is missing, unless ``MVREG_REQUIRE_SHARED=1`` (set by CI), then they fail.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
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


@contextlib.contextmanager
def small_tmpfs(path: Path, size: str = "64k"):
    """Mount a tmpfs of ``size`` on the existing folder ``path`` for the block (a full disk
    on demand); skips the test where mounting is not allowed."""
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                       capture_output=True)  # fmt: skip
    if r.returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield path
    finally:
        subprocess.run(["umount", str(path)], check=False)
