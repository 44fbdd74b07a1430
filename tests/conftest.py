"""Shared test fixtures. Data for tests lives beside the repository in ../shared/data (never copied in)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("STGC_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))

# Two cores: keep torch from oversubscribing when tests run beside numba kernels.
torch.set_num_threads(min(2, os.cpu_count() or 1))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        # A user's fresh clone has no ../shared: these tests check readers and training against the project's
        # shared scenes; every other test runs on generated scenes (tests/scenes.py).
        pytest.skip(f"shared test data not found at {SHARED_DATA} (set STGC_SHARED_DATA to run these tests)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def blender_toys(shared_data: Path) -> Path:
    return shared_data / "blender_toys"


@pytest.fixture(scope="session")
def panoptic_basketball(shared_data: Path) -> Path:
    return shared_data / "panoptic_basketball"
