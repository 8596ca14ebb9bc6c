"""Shared test fixtures.

``shared_datasets``: the research datasets in ``../shared/datasets``. They are never copied into the
repo. When absent, tests that need them skip on a user's machine but fail under CI (``CI=true``).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared")).resolve()


def _require(path: Path) -> Path:
    if not path.exists():
        msg = f"shared data not found: {path}"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(msg + " (required under CI=true)")
        pytest.skip(msg)
    return path


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """``../shared`` (or $GAUSSLITE_SHARED)."""
    return _require(SHARED)


@pytest.fixture(scope="session")
def room0_dir() -> Path:
    """Replica room0 sequence folder (``.../Replica_room0/room0``)."""
    return _require(SHARED / "datasets" / "Replica_room0" / "room0")


@pytest.fixture(scope="session")
def office0_dir() -> Path:
    """Replica office0 sequence folder (4 frames, 2000-line traj.txt)."""
    return _require(SHARED / "datasets" / "Replica_office0" / "office0")


@pytest.fixture(scope="session")
def tum_rpy_dir() -> Path:
    """TUM RGB-D fr1_rpy subset (150 frames)."""
    return _require(SHARED / "datasets" / "TUM_rgbd_dataset_freiburg1_rpy")


@pytest.fixture(scope="session")
def tasks_dir() -> Path:
    """``../shared/tasks`` with phrasings.jsonl."""
    return _require(SHARED / "tasks")
