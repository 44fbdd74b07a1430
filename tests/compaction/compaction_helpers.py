"""Small STG scenes for the compaction tests.

Models are real `stgc.model.STGModel` (lite) instances when that package is importable; otherwise `ToyModel`, a
minimal double with the same contract (params, scene_extent, means_at, rotations_at, prune with Adam state)."""

from __future__ import annotations

import numpy as np
import torch

LITE_WIDTHS = {
    "xyz": 3,
    "scaling": 3,
    "rotation": 4,
    "omega": 4,
    "opacity": 1,
    "trbf_center": 1,
    "trbf_scale": 1,
    "motion": 9,
    "features_dc": 3,
}


class ToyModel:
    """Test double of the STGModel contract (STG formulas: cubic motion, rotation normalize(q + omega * dt))."""

    def __init__(self, params: dict[str, torch.Tensor], scene_extent: float = 1.0):
        self.params = {k: torch.nn.Parameter(v.detach().float().clone()) for k, v in params.items()}
        self.scene_extent = float(scene_extent)
        self.optimizer: torch.optim.Adam | None = None

    @property
    def num_gaussians(self) -> int:
        return int(self.params["xyz"].shape[0])

    def means_at(self, t: float) -> torch.Tensor:
        d = (t - self.params["trbf_center"]).detach()
        m = self.params["motion"]
        return self.params["xyz"] + m[:, 0:3] * d + m[:, 3:6] * d**2 + m[:, 6:9] * d**3

    def rotations_at(self, t: float) -> torch.Tensor:
        d = (t - self.params["trbf_center"]).detach()
        return torch.nn.functional.normalize(self.params["rotation"] + d * self.params["omega"], dim=1)

    def make_optimizer(self, lrs: dict[str, float], decoder_lr: float = 1e-4) -> torch.optim.Adam:
        groups = [{"params": [p], "lr": lrs[k], "name": k} for k, p in self.params.items()]
        self.optimizer = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
        return self.optimizer

    def prune(self, keep: torch.Tensor) -> None:
        for key, old in list(self.params.items()):
            new = torch.nn.Parameter(old.detach()[keep].clone())
            if self.optimizer is not None:
                for group in self.optimizer.param_groups:
                    if group["params"][0] is old:
                        state = self.optimizer.state.pop(old, None)
                        if state is not None:
                            state = {k: (v[keep] if torch.is_tensor(v) and v.dim() > 0 else v) for k, v in state.items()}
                            self.optimizer.state[new] = state
                        group["params"][0] = new
            self.params[key] = new


def make_model(params: dict[str, torch.Tensor], scene_extent: float = 1.0):
    try:
        from stgc.model import STGModel
    except ImportError:
        return ToyModel(params, scene_extent)
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
