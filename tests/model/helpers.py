"""Small builders shared by the model tests."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from stgc.data.cameras import Camera
from stgc.model import SandwichDecoder, STGModel, param_widths


def random_model(variant: str, count: int = 16, seed: int = 0) -> STGModel:
    """A model with every parameter random (so that no formula term can hide behind a zero)."""
    generator = torch.Generator().manual_seed(seed)
    params = {
        key: torch.randn(count, width, generator=generator) * 0.3 for key, width in param_widths(variant).items()
    }
    params["trbf_center"] = torch.rand(count, 1, generator=generator)
    params["opacity"] = torch.randn(count, 1, generator=generator)
    decoder = SandwichDecoder("sigmoid", generator=generator) if variant == "full" else None
    return STGModel(params, variant, scene_extent=1.5, decoder=decoder)


def point_cloud(count: int = 50, seed: int = 0) -> SimpleNamespace:
    rng = np.random.default_rng(seed)
    return SimpleNamespace(
        xyz=rng.normal(size=(count, 3)),
        rgb=rng.uniform(size=(count, 3)),
        time=rng.integers(0, 5, size=count) / 5.0,
    )


def look_at_camera(width: int = 24, height: int = 16, time: float = 0.5, distance: float = 4.0) -> Camera:
    """A camera on the -z axis looking at the origin (OpenCV: +z forward)."""
    focal = 0.8 * width
    K = np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    w2c = np.eye(4)
    w2c[2, 3] = distance
    return Camera(name="cam00", frame=0, time=time, K=K, w2c=w2c, width=width, height=height)
