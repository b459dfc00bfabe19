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


@pytest.fixture(scope="session")
def synth_sequence(tmp_path_factory):
    """Factory of rendered ``metricslam synth`` sequences, each rendered once per session:
    ``synth_sequence(frames, seed=3, path="loop", size=(620, 188)) -> Path`` (KITTI layout)."""
    from metricslam.synth.scene import generate_sequence

    made: dict[tuple, Path] = {}

    def make(frames: int, seed: int = 3, path: str = "loop", size: tuple[int, int] = (620, 188)) -> Path:
        key = (frames, seed, path, tuple(size))
        if key not in made:
            out = tmp_path_factory.mktemp(f"synth_{path}_{frames}_s{seed}")
            generate_sequence(out, frames, seed=seed, size=size, path=path)
            made[key] = out
        return made[key]

    return make
