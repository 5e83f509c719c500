"""Shared fixtures: the real sample data in ``../shared/data``.

Tests that need it use the ``shared_data`` fixture. When the folder is absent
they skip with the reason, unless ``FLEXDOF_REQUIRE_SHARED_DATA=1`` (set by
``.ci/run``), in which case they fail: CI must never skip them silently.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("FLEXDOF_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ``../shared/data``; skip (or fail when required) if it is missing."""
    if SHARED_DATA.is_dir():
        return SHARED_DATA
    reason = f"real sample data not found at {SHARED_DATA} (set FLEXDOF_SHARED_DATA)"
    if os.environ.get("FLEXDOF_REQUIRE_SHARED_DATA") == "1":
        pytest.fail(f"{reason}; FLEXDOF_REQUIRE_SHARED_DATA=1 requires it")
    pytest.skip(reason)


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The project's checkout (for lens_profiles/, stacks/, workflows/)."""
    return REPO_ROOT
