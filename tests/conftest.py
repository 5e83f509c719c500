"""Shared fixtures: the real sample data in ``../shared/data``.

Tests that need it use the ``shared_data`` fixture. When the folder is absent
they skip with the reason, unless ``FLEXDOF_REQUIRE_SHARED_DATA=1`` (set by
``.ci/run``), in which case they fail: CI must never skip them silently.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import pytest
from hypothesis import settings
from hypothesis.database import DirectoryBasedExampleDatabase

# Property tests: reproducible in CI (no randomness, no database: the same examples on
# every run, so a failure is a failure of the change, never of the draw), exploring
# locally (random draws, failures kept in .hypothesis/ and replayed first next time).
# CI is recognised by ``CI`` (set by hosted CI services) or by ``.ci/run``'s
# ``FLEXDOF_REQUIRE_SHARED_DATA=1``; ``HYPOTHESIS_PROFILE`` picks a profile explicitly.
settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
settings.register_profile(
    "dev", database=DirectoryBasedExampleDatabase(".hypothesis/examples"), print_blob=True
)
_IN_CI = bool(os.environ.get("CI")) or os.environ.get("FLEXDOF_REQUIRE_SHARED_DATA") == "1"
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci" if _IN_CI else "dev"))

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


@pytest.fixture(autouse=True)
def _logger_levels():
    """Put back the levels ``flexdof -q``/``-v`` set (``cli.configure_logging``).

    A test that ran ``main(["-q", ...])`` left the ``pipeline`` logger at ERROR, so a
    later test's ``caplog`` saw no warnings: tests passed or failed by their order.
    """
    loggers = [logging.getLogger(name) for name in ("", "pipeline", "tifffile")]
    levels = [log.level for log in loggers]
    yield
    for log, level in zip(loggers, levels, strict=True):
        log.setLevel(level)
