"""Error-guided sampling ("EMS", official STG `train.py`): add Gaussians along the rays of badly reconstructed patches.

Official behaviour (kept): from `ems.start`, record each training camera's SSIM the first time it is rendered; once
every training camera has been seen, the (at most) 2 worst with SSIM < `select_ssim` become candidates (none when
fewer than 2 qualify). When a candidate is rendered again more than `min_gap` iterations after the previous insertion
and its SSIM is below `trigger_ssim`, error pixels are found (brightness-normalised absolute error above its
`error_quantile`), 16x16 patches with more than 85 % error pixels are kept (a 10 % border of patches ignored), 3 of
every 4 pixels inside them (even-even positions skipped) each get 2 Gaussians on their ray at depths
`D·(1 ± 5 %)·{depth_near, depth_far}`, with D the camera's largest median depth. At most `max_events` insertions.
New Gaussians: colour = ground-truth pixel (full variant: with a zero specular feature), opacity 0.1, mu_t ~ U[0,1],
motion/omega/time features 0, scale from the 3-NN distance among the new and the existing points.

Deviations (documented in docs/training.md): the camera depth D is measured when EMS first inserts for that camera
(the official code renders frame 0 before training, from the untrained initial points), and new rotations are the
identity quaternion (the official code writes a zero quaternion, which only its CUDA rasterizer's normalisation
tolerates).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from stgc.data.cameras import Camera
from stgc.model import STGModel, initial_log_scales
from stgc.train.config import EMSConfig


def error_pixels(render: torch.Tensor, gt: torch.Tensor, cfg: EMSConfig) -> np.ndarray:
    """[M, 2] integer (x, y) pixels chosen for insertion (official patch rule), possibly empty."""
    img = render.detach().clamp(0, 1)
    ref = gt.detach()
    diff = (img / img.mean().clamp(min=1e-6) - ref / ref.mean().clamp(min=1e-6)).abs().sum(dim=-1)
    errors = (diff > torch.quantile(diff.flatten(), cfg.error_quantile)).numpy()
    h, w = errors.shape
    p = cfg.patch
    ph, pw = h // p, w // p
    if ph == 0 or pw == 0:
        return np.zeros((0, 2), np.int64)
    fraction = errors[: ph * p, : pw * p].reshape(ph, p, pw, p).mean(axis=(1, 3))
    chosen = fraction > cfg.patch_fraction
    by, bx = int(math.ceil(0.1 * ph)), int(math.ceil(0.1 * pw))
    chosen[:by], chosen[ph - by :], chosen[:, :bx], chosen[:, pw - bx :] = False, False, False, False
    # 3 of every 4 pixels: skip the (even row, even column) ones.
    yy, xx = np.meshgrid(np.arange(p), np.arange(p), indexing="ij")
    inner = ~((yy % 2 == 0) & (xx % 2 == 0))
    offsets = np.stack([xx[inner], yy[inner]], axis=1)
    pixels = [offsets + np.array([bxi * p, byi * p]) for byi, bxi in zip(*np.nonzero(chosen))]
    return np.concatenate(pixels).astype(np.int64) if pixels else np.zeros((0, 2), np.int64)


def ray_points(
    camera: Camera, pixels: np.ndarray, depth: float, cfg: EMSConfig, generator: torch.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """World points on the rays through pixel centres (corner-convention K) at depths D·(1±5%)·{near, far}.

    Returns (xyz [2M, 3], pixel index into `pixels` for each point [2M])."""
    m = len(pixels)
    jitter = 1.0 + 0.05 * (2.0 * torch.rand(m, generator=generator, dtype=torch.float64).numpy() - 1.0)
    base = depth * jitter
    z = np.concatenate([base * cfg.depth_near, base * cfg.depth_far])
    pix = np.concatenate([pixels, pixels]).astype(np.float64) + 0.5
    rays = np.linalg.solve(np.asarray(camera.K, np.float64), np.stack([pix[:, 0], pix[:, 1], np.ones(2 * m)]))
    cam_pts = (rays * z).T  # rays have z = 1, so this is depth along the optical axis
    c2w = np.linalg.inv(np.asarray(camera.w2c, np.float64))
    world = cam_pts @ c2w[:3, :3].T + c2w[:3, 3]
    return world, np.concatenate([np.arange(m), np.arange(m)])


def new_gaussians(
    model: STGModel, xyz: np.ndarray, rgb: np.ndarray, trbf_scale_init: float, generator: torch.Generator
) -> dict[str, torch.Tensor]:
    """Pre-activation parameters of fresh EMS Gaussians (see the module docstring)."""
    n = len(xyz)
    # The 3-NN among the new and the existing Gaussians (the official code's distCUDA2 of both, first n rows).
    existing = model.params["xyz"].detach().cpu().numpy()
    pool = np.concatenate([xyz, existing]).astype(np.float32)
    log_scale = torch.as_tensor(initial_log_scales(pool[:n], 3, among=pool), dtype=torch.float32)
    rgb_t = torch.as_tensor(rgb, dtype=torch.float32)
    new = {
        "xyz": torch.as_tensor(xyz, dtype=torch.float32),
        "scaling": log_scale.reshape(n, 1).repeat(1, 3),
        "rotation": torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        "omega": torch.zeros(n, 4),
        "opacity": torch.full((n, 1), math.log(0.1 / 0.9)),
        "trbf_center": torch.rand(n, 1, generator=generator),
        "trbf_scale": torch.full((n, 1), float(trbf_scale_init)),
        "motion": torch.zeros(n, 9),
        # Full: the base colour and a zero specular feature, as the official addgaussians; lite: the colour.
        "features_dc": torch.cat([rgb_t, torch.zeros_like(rgb_t)], dim=1) if model.params["features_dc"].shape[1] == 6
        else rgb_t,
    }
    if "features_t" in model.params:
        new["features_t"] = torch.zeros(n, 3)
    return new


class ErrorGuidedSampler:
    """The EMS state machine; its `state` dict is saved in the training checkpoint."""

    def __init__(self, cfg: EMSConfig, start: int, min_gap: int, train_names: list[str], trbf_scale_init: float,
                 backend: str = "auto"):
        self.cfg, self.start, self.min_gap = cfg, start, min_gap
        self.backend = backend  # the training renders' (train.backend): the depth it reads rounds as they do
        self.train_names = sorted(set(train_names))
        self.trbf_scale_init = trbf_scale_init
        self.state: dict[str, Any] = {"ssim": {}, "depth": {}, "candidates": None, "events": 0, "last": -10**9}

    def listening(self, iteration: int) -> bool:
        """Whether `observe` uses the views' SSIM at `iteration`."""
        return bool(self.cfg.enabled and iteration >= self.start and self.state["events"] < self.cfg.max_events)

    def observe(self, iteration: int, camera: Camera, ssim_value: float, last_of_batch: bool = True) -> bool:
        """Record a rendered training view; True when this view should trigger an insertion. As the official loop,
        only the batch's last view may trigger, and a candidate rendered more than `min_gap` iterations after the
        previous event makes an event whatever its SSIM: the event counts, and it inserts only below the trigger
        SSIM. A candidate stays one (the official loop never removes it; before 2026-11-28 stgc did), so one camera
        may take both events."""
        st, cfg = self.state, self.cfg
        if not self.listening(iteration):
            return False
        name = str(camera.name)
        st["ssim"].setdefault(name, float(ssim_value))
        if st["candidates"] is None:
            if len(st["ssim"]) < len(self.train_names):
                return False
            poor = sorted((s, n) for n, s in st["ssim"].items() if s < cfg.select_ssim)[:2]
            st["candidates"] = [n for _, n in poor] if len(poor) == 2 else []
            return False  # candidates act from their next render on
        if not last_of_batch or name not in st["candidates"] or iteration - st["last"] <= self.min_gap:
            return False
        st["events"] += 1
        st["last"] = iteration
        return bool(ssim_value < cfg.trigger_ssim)

    def camera_depth(self, model: STGModel, camera: Camera) -> float:
        """The largest median depth the model shows in this camera (cached per camera name)."""
        name = str(camera.name)
        if name not in self.state["depth"]:
            with torch.no_grad():
                out = model.render(camera, t=float(camera.time), backend=self.backend, return_depth=True)
            depth = out.depth
            valid = depth[depth > 0] if depth is not None else torch.zeros(0)
            self.state["depth"][name] = float(valid.max()) if valid.numel() else float("nan")
        return self.state["depth"][name]

    def insert(self, iteration: int, model: STGModel, camera: Camera, render: torch.Tensor, gt: torch.Tensor,
               generator: torch.Generator) -> int:
        """Add Gaussians for `camera`'s error patches (an event `observe` counted); returns how many were added."""
        depth = self.camera_depth(model, camera)
        pixels = error_pixels(render, gt, self.cfg)
        if not len(pixels) or not math.isfinite(depth):
            return 0
        xyz, which = ray_points(camera, pixels, depth, self.cfg, generator)
        rgb = gt.detach().numpy()[pixels[which, 1], pixels[which, 0]]
        model.extend(new_gaussians(model, xyz, rgb, self.trbf_scale_init, generator))
        return len(xyz)
