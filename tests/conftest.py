"""Shared fixtures: the reference data folder (never copied into the repository)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent


def _find_shared_data() -> Path | None:
    env = os.environ.get("DOPE_HOPE_SHARED_DATA")
    candidates = [Path(env)] if env else []
    candidates += [REPO_ROOT.parent / "shared" / "data", REPO_ROOT / "shared" / "data"]
    for c in candidates:
        if (c / "hope_ketchup" / "textured.obj").is_file():
            return c
    return None


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` (or $DOPE_HOPE_SHARED_DATA); skips when it is absent."""
    path = _find_shared_data()
    if path is None:
        pytest.skip("reference data ../shared/data not found (set DOPE_HOPE_SHARED_DATA); "
                    "its license forbids shipping it with the repository")
    return path


@pytest.fixture(scope="session")
def ketchup_obj(shared_data: Path) -> Path:
    return shared_data / "hope_ketchup" / "textured.obj"
