"""The numba projection (forward and hand-written backward) against the torch projection and finite differences,
on Gaussians that take every branch: inside the frustum, beyond the x/y clamp of the Jacobian, behind the near
plane, and with a degenerate (clamped) 2D determinant."""

from __future__ import annotations

import pytest
import torch

from stgc.render.numba_backend import project_numba
from stgc.render.projection import project_gaussians

from .scenes import make_scene


def _branchy_scene(dtype: torch.dtype):
    scene = make_scene(40, width=48, height=36, focal=40.0, seed=7, dtype=dtype)
    means = scene.means.clone()
    cam_R, cam_t = scene.viewmat[:3, :3], scene.viewmat[:3, 3]
    cam = means @ cam_R.T + cam_t
    cam[0:6, 0] += 4.0 * cam[0:6, 2]  # far right of the image: x/z beyond the clamp limit
    cam[6:10, 1] -= 3.0 * cam[6:10, 2]  # far above: y/z clamped
    cam[10:13, 2] = 0.1  # in front of the camera but closer than the near plane
    cam[13:15, 2] = -2.0  # behind the camera
    scales = scene.scales.clone()
    scales[15:17] = 1e-9  # a degenerate footprint: only the dilation remains; and one flat axis
    scales[17, :2] = 1e-9
    return scene, (cam - cam_t) @ cam_R, scales


def _project(fn, scene, means, scales):
    return fn(means, scene.quats, scales, scene.opacities, scene.K, scene.viewmat, scene.width, scene.height,
              eps2d=0.3, near_plane=0.2)  # fmt: skip


@pytest.mark.parametrize("eps2d", [0.3, 0.0])  # without the dilation, the degenerate footprints clamp det
def test_numba_projection_matches_torch_on_every_branch(eps2d):
    scene, means, scales = _branchy_scene(torch.float64)
    g = torch.Generator().manual_seed(2)
    w_m, w_c = torch.randn(40, 2, generator=g, dtype=torch.float64), torch.randn(40, 3, generator=g, dtype=torch.float64)
    results = []
    for fn in (project_numba, project_gaussians):
        leaves = [t.detach().clone().requires_grad_(True) for t in (means, scene.quats, scales)]
        p = fn(leaves[0], leaves[1], leaves[2], scene.opacities, scene.K, scene.viewmat, scene.width,
               scene.height, eps2d=eps2d, near_plane=0.2)  # fmt: skip
        ((p.means2d * w_m).sum() + (p.conics * w_c).sum()).backward()
        results.append((p, [t.grad for t in leaves]))
    (a, ga), (b, gb) = results
    assert torch.equal(a.radii, b.radii) and torch.equal(a.visible, b.visible)
    assert not bool(a.visible[10:15].any())  # near-plane and behind-camera Gaussians are culled
    assert bool(a.visible.any())
    for x, y in [(a.means2d, b.means2d), (a.conics, b.conics), (a.depths, b.depths)] + list(zip(ga, gb)):
        assert torch.allclose(x, y, rtol=1e-9, atol=1e-9), (x - y).abs().max()


def test_numba_projection_gradients_against_finite_differences():
    scene, means, scales = _branchy_scene(torch.float64)
    keep = torch.cat([torch.arange(0, 10), torch.arange(15, 40)])  # culled Gaussians have no gradient to check; the clamp branches are in
    quats = scene.quats[keep]

    def f(m, q, s):
        p = project_numba(m, q, s, scene.opacities[keep], scene.K, scene.viewmat, scene.width, scene.height,
                          eps2d=0.3, near_plane=0.2)  # fmt: skip
        return p.means2d, p.conics

    inputs = [t.detach().clone().requires_grad_(True) for t in (means[keep], quats, scales[keep].abs() + 1e-3)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-7, atol=1e-5, rtol=1e-4)


def test_float32_projection_agrees_with_float64():
    scene, means, scales = _branchy_scene(torch.float64)
    p64 = _project(project_numba, scene, means, scales)
    s32 = make_scene(40, width=48, height=36, focal=40.0, seed=7, dtype=torch.float32)
    p32 = project_numba(means.float(), s32.quats, scales.float(), s32.opacities, s32.K, s32.viewmat, 48, 36,
                        eps2d=0.3, near_plane=0.2)  # fmt: skip
    assert p32.means2d.dtype == torch.float32
    visible = p64.visible
    assert torch.equal(p32.visible, visible)
    assert torch.allclose(p32.means2d[visible].double(), p64.means2d[visible], rtol=1e-5, atol=1e-3)
    # The conics carry the quaternions and scales; near-degenerate footprints are ill-conditioned, so relative to
    # the largest entry of each Gaussian's conic.
    scale = p64.conics[visible].abs().amax(-1, keepdim=True)
    assert ((p32.conics[visible].double() - p64.conics[visible]).abs() / scale).max() < 1e-4


def test_camera_gradients_are_refused_not_dropped():
    scene = make_scene(5, seed=1)
    K = scene.K.clone().requires_grad_(True)
    with pytest.raises(ValueError, match="no gradient for K or viewmat"):
        project_numba(scene.means, scene.quats, scene.scales, scene.opacities, K, scene.viewmat, scene.width,
                      scene.height, eps2d=0.3, near_plane=0.2)  # fmt: skip
