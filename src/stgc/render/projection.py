"""EWA projection of 3D Gaussians to the image plane, shared by every compositing backend.

The math is gsplat 1.5.3's pinhole projection (`_fully_fused_projection` / ProjectionEWA3DGSFused.cu):

* covariance  Sigma = R S S^T R^T with R from the normalised quaternion (w, x, y, z);
* camera frame: OpenCV world-to-camera `viewmat`; Gaussians with depth <= near_plane (or >= far_plane) are culled;
* Jacobian of the pinhole map, evaluated at the camera-space mean whose x/z and y/z are clamped to
  1.3 x the half field of view (0.3 tan(fov/2) beyond each image border, as gsplat and Inria do), which keeps the
  footprint of Gaussians far outside the frustum bounded;
* cov2d = J Sigma_c J^T + eps2d I (eps2d = 0.3 px^2: the "low-pass filter" dilation of 3DGS);
* conic = inverse of cov2d as (a, b, c) with sigma = 1/2 (a dx^2 + c dy^2) + b dx dy;
* means2d = K[:2] @ mean_c / z, so pixel centres sit at integer + 0.5 (the gsplat / COLMAP convention);
* screen radius per axis = ceil(extent * sqrt(cov2d_ii)) with extent = min(3.33, sqrt(2 ln(255 o))): the
  opacity-aware box of gsplat's CUDA projection. Outside it o * exp(-sigma) < 1/255, so the compositor would skip the
  pixel anyway; the bound is exact and only removes tile intersections. Gaussians with o < 1/255 are culled.

This module runs in torch (autograd), so it works unchanged on any device: the torch backend uses it, and it is the
oracle of the numba backend's own projection kernel (`_numba_projection.py`, the same math in one pass per
Gaussian, tested against this to 1e-9 in float64).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeVar

import torch
from torch import Tensor

T = TypeVar("T", float, Tensor)

# 1/255: below this alpha a Gaussian is skipped (3DGS / gsplat ALPHA_THRESHOLD).
ALPHA_MIN = 1.0 / 255.0
# Radius cap in standard deviations (gsplat's 3.33; at o = 1 the opacity-aware bound sqrt(2 ln 255) = 3.3296 is
# already below it, so for o <= 1 the cap never binds).
RADIUS_SIGMAS = 3.33
# Largest radius we report; keeps the int32 cast of astronomically large footprints defined.
MAX_RADIUS = float(2**30)
# Floor of the 2D covariance determinant before the conic divides by it.
DET_MIN = 1e-10
# Margin (in sigma units) for the per-Gaussian "skip before exp" bound: float32 exp/log rounding is ~1e-7 relative,
# so a 1e-3 margin keeps the cut strictly conservative (the exact alpha test still decides inside the margin).
SIGMA_CUT_MARGIN = 1e-3


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities for one camera (N = number of input Gaussians, culled ones included)."""

    means2d: Tensor  # [N, 2] pixels, differentiable
    conics: Tensor  # [N, 3] (a, b, c), differentiable
    depths: Tensor  # [N] camera-space z, no gradient
    radii: Tensor  # [N, 2] int32, 0 = culled
    visible: Tensor  # [N] bool


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N, 4] (w, x, y, z), any norm -> [N, 3, 3] rotation matrices."""
    q = torch.nn.functional.normalize(quats, p=2.0, dim=-1)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(q.shape[:-1] + (3, 3))


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    K: Tensor,
    viewmat: Tensor,
    width: int,
    height: int,
    *,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
) -> Projected:
    """Project N Gaussians into one pinhole camera (see the module docstring for the conventions)."""
    Rv, tv = viewmat[:3, :3], viewmat[:3, 3]
    means_cam = means @ Rv.T + tv
    tx, ty, tz = means_cam.unbind(-1)

    # Culled-by-depth Gaussians get a harmless stand-in depth before any division, so that neither the forward nor
    # the backward pass produces inf/NaN for them (a `where` after the division would still leak NaN gradients).
    in_depth = (tz > near_plane) & (tz < far_plane)
    z = torch.where(in_depth, tz, torch.ones_like(tz))

    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos = jacobian_limits(fx, fy, cx, cy, width, height)
    tx_c = z * torch.clamp(tx / z, min=-lim_x_neg, max=lim_x_pos)
    ty_c = z * torch.clamp(ty / z, min=-lim_y_neg, max=lim_y_pos)

    # cov2d = J Rv R S S^T R^T Rv^T J^T = A A^T with A = (J Rv) R S, J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]].
    # Building the [N, 2, 3] factor directly avoids chains of batched 3x3 products (slow on CPU), same math as gsplat.
    inv_z = 1.0 / z
    row0 = (fx * inv_z)[:, None] * Rv[0] - (fx * tx_c * inv_z * inv_z)[:, None] * Rv[2]
    row1 = (fy * inv_z)[:, None] * Rv[1] - (fy * ty_c * inv_z * inv_z)[:, None] * Rv[2]
    JW = torch.stack([row0, row1], dim=1)  # [N, 2, 3]
    A = torch.bmm(JW, quat_to_rotmat(quats)) * scales[:, None, :]
    a0, a1 = A[:, 0], A[:, 1]
    c00 = (a0 * a0).sum(-1) + eps2d
    c11 = (a1 * a1).sum(-1) + eps2d
    c01 = (a0 * a1).sum(-1)
    det_raw = c00 * c11 - c01 * c01
    det = det_raw.clamp(min=DET_MIN)
    conics = torch.stack([c11 / det, -c01 / det, c00 / det], dim=-1)

    means2d = (means_cam @ K[:2, :3].T) / z[:, None]

    with torch.no_grad():
        radii, visible = _screen_radii(
            means2d, c00, c11, det_raw, opacities, in_depth, width, height
        )
    return Projected(means2d=means2d, conics=conics, depths=tz.detach(), radii=radii, visible=visible)


def jacobian_limits(fx: T, fy: T, cx: T, cy: T, width: int, height: int) -> tuple[T, T, T, T]:
    """(x-, x+, y-, y+): how far x/z and y/z may reach before the Jacobian is evaluated at the clamped point
    (0.3 tan(fov/2) beyond each image border). Plain arithmetic: floats or tensors alike."""
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    return (cx / fx + 0.3 * tan_fovx, (width - cx) / fx + 0.3 * tan_fovx,
            cy / fy + 0.3 * tan_fovy, (height - cy) / fy + 0.3 * tan_fovy)


def _screen_radii(
    means2d: Tensor,
    var_x: Tensor,
    var_y: Tensor,
    det: Tensor,
    opacities: Tensor,
    in_depth: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    opac = opacities.detach().to(var_x.dtype)
    # At or below DET_MIN the conic is clamped to nearly 0, which would paint the whole box at full opacity: with
    # eps2d 0 such a footprint is far below a pixel (sub-1e-5 px), so it is culled, not drawn as a tile-sized square.
    keep = in_depth & (det > DET_MIN) & (opac >= ALPHA_MIN)
    # sqrt(2 ln(255 o)) is where o * exp(-sigma) reaches 1/255 on the ellipse's principal axes.
    extent = torch.sqrt(2.0 * torch.log(torch.clamp(opac, min=ALPHA_MIN) * 255.0)).clamp(max=RADIUS_SIGMAS)
    rx = torch.ceil(extent * torch.sqrt(var_x.detach().clamp(min=0))).clamp(max=MAX_RADIUS)
    ry = torch.ceil(extent * torch.sqrt(var_y.detach().clamp(min=0))).clamp(max=MAX_RADIUS)
    m = means2d.detach()
    inside = (m[:, 0] + rx > 0) & (m[:, 0] - rx < width) & (m[:, 1] + ry > 0) & (m[:, 1] - ry < height)
    visible = keep & inside & ((rx > 0) | (ry > 0)) & torch.isfinite(m).all(-1)
    radii = torch.stack([rx, ry], dim=-1)
    radii = torch.where(visible[:, None], radii, torch.zeros_like(radii)).to(torch.int32)
    return radii, visible


def tile_grid(width: int, height: int, tile_size: int) -> tuple[int, int]:
    return math.ceil(width / tile_size), math.ceil(height / tile_size)


def tile_rects(radii: Tensor, means2d: Tensor, width: int, height: int, tile_size: int) -> Tensor:
    """[N, 4] int64 (x0, y0, x1, y1) half-open tile ranges covered by each Gaussian's box; empty for culled ones.

    Same rule as gsplat: [floor((m - r) / ts), ceil((m + r) / ts)) clamped to the grid."""
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    m = means2d.detach().to(torch.float64) / tile_size
    r = radii.to(torch.float64) / tile_size
    lo = torch.floor(m - r)
    hi = torch.ceil(m + r)
    x0 = lo[:, 0].clamp(0, tiles_x)
    x1 = hi[:, 0].clamp(0, tiles_x)
    y0 = lo[:, 1].clamp(0, tiles_y)
    y1 = hi[:, 1].clamp(0, tiles_y)
    rect = torch.stack([x0, y0, x1, y1], dim=-1).to(torch.int64)
    culled = (radii <= 0).all(-1)
    rect[culled] = 0
    return rect


@torch.no_grad()
def bin_tiles_torch(
    rect: Tensor, depths: Tensor, visible: Tensor, width: int, height: int, tile_size: int
) -> tuple[Tensor, Tensor]:
    """Device-agnostic tile binning: (tile_offsets [T+1] int64, flat_ids [M] int64 sorted by (tile, depth)).

    Ties in depth keep the input order (stable), which the numba binning reproduces exactly."""
    device = rect.device
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    n_tiles = tiles_x * tiles_y
    N = rect.shape[0]
    nx = (rect[:, 2] - rect[:, 0]).clamp(min=0)
    ny = (rect[:, 3] - rect[:, 1]).clamp(min=0)
    count = nx * ny * visible.to(torch.int64)
    M = int(count.sum())
    offsets = torch.zeros(n_tiles + 1, dtype=torch.int64, device=device)
    if M == 0:
        return offsets, torch.zeros(0, dtype=torch.int64, device=device)
    gid = torch.repeat_interleave(torch.arange(N, device=device), count)
    first = torch.cumsum(count, 0) - count
    local = torch.arange(M, device=device) - first[gid]
    lx = local % nx[gid]
    ly = torch.div(local, nx[gid], rounding_mode="floor")
    tile = (rect[gid, 1] + ly) * tiles_x + (rect[gid, 0] + lx)
    order = torch.argsort(depths, stable=True)
    rank = torch.empty(N, dtype=torch.int64, device=device)
    rank[order] = torch.arange(N, device=device)
    key, _ = torch.sort(tile * N + rank[gid])
    flat_ids = order[key % N]
    offsets[1:] = torch.cumsum(torch.bincount(torch.div(key, N, rounding_mode="floor"), minlength=n_tiles), 0)
    return offsets, flat_ids
