"""Shared test fixtures.

``shared_data`` points at ``../shared/data`` beside the repository (present for developers and
CI, never on a user's machine); tests that need it are skipped with a reason when it is absent.
Override with ``METRICSLAM_SHARED_DATA=/path``.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path:
    env = os.environ.get("METRICSLAM_SHARED_DATA")
    return Path(env) if env else (REPO_ROOT.parent / "shared" / "data")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    path = shared_data_dir()
    if not path.is_dir():
        pytest.skip(f"real data folder {path} is absent (set METRICSLAM_SHARED_DATA to use one)")
    return path


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT
