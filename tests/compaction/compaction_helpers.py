"""Small STG scenes for the compaction tests, as real `stgc.model.STGModel` (lite) instances."""

from __future__ import annotations

import numpy as np
import torch

from stgc.compaction import PAPER_RULE, CompactionConfig
from stgc.model import STGModel, param_widths

LITE_WIDTHS = param_widths("lite")


def make_model(params: dict[str, torch.Tensor], scene_extent: float = 1.0) -> STGModel:
    return STGModel(params, "lite", scene_extent=scene_extent)


def static_params(xyz: np.ndarray, trbf_center: np.ndarray | float = 0.5) -> dict[str, torch.Tensor]:
    """Static Gaussians (no motion, identity rotation) at the given positions."""
    n = xyz.shape[0]
    params = {k: torch.zeros(n, w) for k, w in LITE_WIDTHS.items()}
    params["xyz"] = torch.as_tensor(xyz, dtype=torch.float32)
    params["rotation"][:, 0] = 1.0
    params["scaling"][:] = -3.0
    params["trbf_center"][:, 0] = torch.as_tensor(trbf_center, dtype=torch.float32)
    return params


def random_params(n: int, seed: int, motion_scale: float = 0.3) -> dict[str, torch.Tensor]:
    """A random dynamic scene: positions in a unit cube, random rotations, random cubic motion and omega."""
    g = torch.Generator().manual_seed(seed)
    params = {k: torch.randn(n, w, generator=g) for k, w in LITE_WIDTHS.items()}
    params["xyz"] = torch.rand(n, 3, generator=g)
    params["trbf_center"] = torch.rand(n, 1, generator=g)
    params["motion"] *= motion_scale
    params["omega"] *= 0.5
    params["scaling"] = params["scaling"] * 0.3 - 4.0
    return params


def paper_rule(**options) -> CompactionConfig:
    """A CompactionConfig of the paper's rule as written (PAPER_RULE; stgc's defaults differ since session 37),
    with `options` on top: the scripted-loss tests drive the paper's step-to-step controller."""
    return CompactionConfig(**{**PAPER_RULE, **options})
