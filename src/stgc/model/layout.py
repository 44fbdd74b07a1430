"""The official Spacetime Gaussians PLY layout (oppo-us-research/SpacetimeGaussians `save_ply`).

One float32 per field, stored pre-activation, in exactly this order. The three normals are written
as zeros by the official code and never read; the paper's 152 bytes per Gaussian counts them.
"""

from __future__ import annotations

from typing import Literal, get_args

Variant = Literal["full", "lite"]
VARIANTS = get_args(Variant)


def ply_fields(variant: str) -> list[str]:
    """Field names of one Gaussian's row, in file order."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown STG variant {variant!r}; expected one of {VARIANTS}")
    n_dc = 6 if variant == "full" else 3
    fields = ["x", "y", "z", "trbf_center", "trbf_scale", "nx", "ny", "nz"]
    fields += [f"motion_{i}" for i in range(9)]
    fields += [f"f_dc_{i}" for i in range(n_dc)]
    fields += ["opacity"]
    fields += [f"scale_{i}" for i in range(3)]
    fields += [f"rot_{i}" for i in range(4)]
    fields += [f"omega_{i}" for i in range(4)]
    if variant == "full":
        fields += [f"f_t_{i}" for i in range(3)]
    return fields


NORMAL_FIELDS = ("nx", "ny", "nz")


def bytes_per_gaussian(variant: str, include_normals: bool = True) -> int:
    """Raw float32 bytes of one PLY row: full 152 (140 without normals), lite 128 (116)."""
    n = len(ply_fields(variant))
    if not include_normals:
        n -= len(NORMAL_FIELDS)
    return 4 * n
