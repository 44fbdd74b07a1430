"""A tiny training scene: a few frames of blender_toys at half resolution, initialised from its surface samples."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from stgc.data import open_dataset
from stgc.model import STGModel


def tiny_model(dataset, points_per_frame: int = 500, variant: str = "full", seed: int = 0) -> STGModel:
    rng = np.random.default_rng(seed)
    xyz, rgb, time = [], [], []
    for frame in dataset.frames:
        pts = dataset.data_points(frame)
        assert pts is not None, "blender_toys ships per-frame points"
        p, c = pts
        pick = rng.choice(len(p), size=min(points_per_frame, len(p)), replace=False)
        xyz.append(p[pick])
        rgb.append(c[pick])
        time.append(np.full(len(pick), dataset.time_of(frame)))
    cloud = SimpleNamespace(
        xyz=np.concatenate(xyz).astype(np.float32),
        rgb=np.concatenate(rgb).astype(np.float32),
        time=np.concatenate(time).astype(np.float32),
    )
    return STGModel.from_points(cloud, variant=variant, scene_extent=dataset.scene_extent())


@pytest.fixture(scope="session")
def tiny_toys(blender_toys):
    """80x60, 3 frames, 15 training views + cam00 held out."""
    return open_dataset(blender_toys, downscale=2, start=0, duration=3)


@pytest.fixture(scope="session")
def make_model():
    """tiny_model as a fixture (test modules here are not a package, so they cannot import conftest)."""
    return tiny_model
