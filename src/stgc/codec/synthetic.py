"""Synthetic STG models with the statistics of trained ones, for codec tests and benchmarks.

The shapes follow what training produces (see /shared/reference/stg_official_code.md): Gaussians sit on surfaces and
in clusters (so Morton order finds locality), a small share are distant background; many are static (motion near 0,
omega exactly 0 after the official omega freeze); trbf_center stays near the frame time it was initialised at;
raw quaternions drift off unit norm; opacity logits are bimodal; log-scales are anisotropic around 1 % of the scene.
"""

from __future__ import annotations

import numpy as np

from stgc.model.layout import ply_fields

__all__ = ["synthetic_model"]


def _positions(rng: np.random.Generator, n: int, extent: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions [n, 3] and the id of the surface patch / cluster each belongs to (far points: their own ids)."""
    n_far = n // 10
    n_cluster = n * 3 // 10
    n_surface = n - n_far - n_cluster
    # Surfaces: random planes patches (walls, floor, objects' faces) with a little thickness.
    n_planes = max(1, n_surface // 2000)
    plane = rng.integers(0, n_planes, n_surface)
    origin = rng.uniform(-extent, extent, (n_planes, 3))
    basis = np.linalg.qr(rng.normal(size=(n_planes, 3, 3)))[0]
    uv = rng.uniform(-0.5 * extent, 0.5 * extent, (n_surface, 2))
    surface = (origin[plane] + basis[plane, :, 0] * uv[:, :1] + basis[plane, :, 1] * uv[:, 1:]
               + basis[plane, :, 2] * rng.normal(0, 0.002 * extent, (n_surface, 1)))
    centres = rng.uniform(-extent, extent, (max(1, n_cluster // 300), 3))
    far = rng.normal(size=(n_far, 3))
    far *= (rng.uniform(3, 8, (n_far, 1)) * extent) / np.linalg.norm(far, axis=1, keepdims=True)
    cluster_id = rng.integers(0, len(centres), n_cluster)
    cluster = centres[cluster_id] + rng.normal(0, 0.03 * extent, (n_cluster, 3))
    far_id = rng.integers(0, max(1, n_far // 100), n_far)
    xyz = np.concatenate([surface, cluster, far])
    group = np.concatenate([plane, n_planes + cluster_id, n_planes + len(centres) + far_id])
    shuffle = rng.permutation(n)
    return xyz[shuffle], group[shuffle]


def synthetic_model(n: int, variant: str = "full", seed: int = 0, extent: float = 3.0,
                    frames: int = 50) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray] | None]:
    """Official-layout float32 arrays (ply_fields order) and, for "full", a sandwich-decoder state dict."""
    rng = np.random.default_rng(seed)
    cols: dict[str, np.ndarray] = {}
    xyz, group = _positions(rng, n, extent)
    n_groups = int(group.max()) + 1
    for i, axis in enumerate("xyz"):
        cols[axis] = xyz[:, i]
    cols["trbf_center"] = rng.integers(0, frames, n) / frames + rng.normal(0, 0.01, n)
    cols["trbf_scale"] = np.clip(rng.normal(-0.8, 0.6, n), -4.0, 1.5)
    for name in ("nx", "ny", "nz"):
        cols[name] = np.zeros(n)
    dynamic = rng.random(n) < 0.35
    for k, scale in enumerate((0.05, 0.02, 0.01)):  # linear, quadratic, cubic coefficients per axis
        for component in range(3):
            m = np.where(dynamic, rng.laplace(0, scale * extent, n), rng.normal(0, 1e-4, n))
            cols[f"motion_{3 * k + component}"] = m
    n_dc = 6 if variant == "full" else 3
    # Colour and size are coherent per surface patch / cluster (texture varies around a base), as in real scenes;
    # the colour channels share the patch's brightness, so they are strongly correlated (as in trained models).
    brightness = rng.beta(2.0, 2.5, (n_groups, 1))[group] + rng.normal(0, 0.1, (n, 1))
    base = brightness + rng.normal(0, 0.06, (n_groups, 3))[group] + rng.normal(0, 0.03, (n, 3))
    for c in range(n_dc):
        if c < 3:
            cols[f"f_dc_{c}"] = base[:, c] + rng.normal(0, 0.02, n)
        else:  # specular / view-dependent half of the full model's features: small, centred
            cols[f"f_dc_{c}"] = rng.laplace(0, 0.08, n)
    opaque = rng.random(n) < 0.6
    cols["opacity"] = np.where(opaque, rng.normal(3.0, 1.5, n), rng.normal(-3.0, 1.5, n))
    log_scale = (np.log(0.01 * extent) + rng.normal(0, 0.6, (n_groups, 1))[group] + rng.normal(0, 0.6, (n, 1))
                 + rng.normal(0, 0.5, (n, 3)))
    log_scale = np.clip(log_scale, -10.0, 1.0)
    for i in range(3):
        cols[f"scale_{i}"] = log_scale[:, i]
    quat = rng.normal(size=(n, 4))
    quat *= rng.normal(1.0, 0.15, (n, 1)) / np.linalg.norm(quat, axis=1, keepdims=True)
    for i in range(4):
        cols[f"rot_{i}"] = quat[:, i]
    rotating = dynamic & (rng.random(n) < 0.5)
    for i in range(4):
        cols[f"omega_{i}"] = np.where(rotating, rng.laplace(0, 0.05, n), 0.0)
    if variant == "full":
        for i in range(3):
            cols[f"f_t_{i}"] = rng.laplace(0, 0.05, n)
    arrays = {name: cols[name].astype(np.float32) for name in ply_fields(variant)}
    decoder = None
    if variant == "full":
        decoder = {
            "mlp1.weight": rng.normal(0, 0.3, (6, 12, 1, 1)).astype(np.float32),
            "mlp2.weight": rng.normal(0, 0.4, (3, 6, 1, 1)).astype(np.float32),
        }
    return arrays, decoder
