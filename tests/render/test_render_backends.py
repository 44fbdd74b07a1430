"""Backend selection, the gsplat path's wiring and fallback (on CPU), and the auxiliary outputs."""

from __future__ import annotations

import os
import subprocess
import sys
import types
import warnings
from pathlib import Path

import pytest
import torch

from stgc.render import (
    api,
    available_backends,
    gsplat_backend,
    rasterize,
    select_backend,
)

from .scenes import make_scene

REPO = Path(__file__).resolve().parents[2]


def test_selection_on_a_cpu_machine():
    assert available_backends()[:2] == ["numba", "torch"]
    assert select_backend("auto", torch.device("cpu")) == "numba"
    assert select_backend("torch", torch.device("cpu")) == "torch"
    assert select_backend("auto", torch.device("meta")) == "torch"
    with pytest.raises(ValueError, match="needs CUDA tensors"):
        select_backend("gsplat", torch.device("cpu"))
    with pytest.raises(ValueError, match="needs CPU tensors"):
        select_backend("numba", torch.device("meta"))


def test_auto_on_cpu_never_imports_gsplat():
    # A fresh interpreter: the test process itself has gsplat loaded for the oracle.
    code = (
        "import sys, torch\n"
        "from stgc.render import rasterize, available_backends\n"
        "available_backends()\n"
        "out = rasterize(torch.zeros(1, 3) + torch.tensor([0., 0., 3.]), torch.tensor([[1., 0, 0, 0]]),\n"
        "                torch.full((1, 3), 0.1), torch.tensor([0.5]), torch.ones(1, 3), torch.eye(3) * 8, torch.eye(4),\n"
        "                4, 4)\n"
        "assert out.backend == 'numba', out.backend\n"
        "assert 'gsplat' not in sys.modules\n"
    )
    env = dict(os.environ, PYTHONPATH=str(REPO / "src"))
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr


def _fake_gsplat():
    """A stand-in for gsplat's CUDA entry points, built from gsplat's own torch reference (with the test shim), so
    that the wiring of our gsplat path (argument order, batch dims, means2d gradient) runs on CPU."""
    from gsplat.cuda import _torch_impl as impl

    from .gsplat_oracle import _fake_nerfacc, _indices_in_range

    def fully_fused_projection(means, covars, quats, scales, viewmats, Ks, width, height, *, eps2d, near_plane,
                               opacities=None):  # fmt: skip  (no defaults: the backend must pass what it was given)
        assert covars is None and opacities is not None and opacities.shape == means.shape[:1]
        if means.shape[0] == 0:  # gsplat 1.5.3 divides by N on the host: a SIGFPE that kills the process
            raise ZeroDivisionError("fully_fused_projection with no Gaussians")
        covars, _ = impl._quat_scale_to_covar_preci(quats, scales, True, False)
        return impl._fully_fused_projection(means, covars, viewmats, Ks, width, height, eps2d, near_plane)

    def rasterize_to_pixels(means2d, conics, colors, opacities, width, height, tile_size, offsets, flat,
                            backgrounds=None):  # fmt: skip
        from unittest import mock

        import gsplat.cuda._wrapper as wrapper

        with mock.patch.dict(sys.modules, {"nerfacc": _fake_nerfacc}), mock.patch.object(
            wrapper, "rasterize_to_indices_in_range", _indices_in_range
        ):
            return impl._rasterize_to_pixels(means2d, conics, colors, opacities, width, height, tile_size, offsets,
                                             flat, backgrounds=backgrounds)  # fmt: skip

    return types.SimpleNamespace(
        __version__="1.5.3",
        fully_fused_projection=fully_fused_projection,
        isect_tiles=impl._isect_tiles,
        isect_offset_encode=impl._isect_offset_encode,
        rasterize_to_pixels=rasterize_to_pixels,
    )


@pytest.fixture
def fresh_gsplat_state(monkeypatch):
    monkeypatch.setattr(gsplat_backend, "_state", {"module": None, "failure": None, "alpha_warned": False})
    monkeypatch.setattr(api, "select_backend", lambda requested, device: "gsplat")


def test_gsplat_path_wiring_matches_numba(fresh_gsplat_state, monkeypatch):
    monkeypatch.setattr(gsplat_backend, "_import_gsplat", _fake_gsplat)
    scene = make_scene(400, 48, 32, channels=9, principal_offset=(2.5, -1.5), seed=4)
    bg = torch.linspace(0.2, 0.8, 9)
    outs = {}
    for backend in ("gsplat", "numba"):
        s = scene.leaves()
        if backend == "numba":
            monkeypatch.setattr(api, "select_backend", lambda requested, device: "numba")
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # alpha_max matches gsplat 1.5.3's compiled-in 0.999: no warning
            out = rasterize(*s.args(), bg, backend=backend, alpha_max=0.999, return_depth=True, return_weights=True,
                            eps2d=0.1, near_plane=3.5)  # not the defaults: each backend must pass them on
        assert out.backend == backend
        out.image.sum().backward()
        outs[backend] = (out, s.means.grad, s.features.grad)
    (a, ma, fa), (b, mb, fb) = outs["gsplat"], outs["numba"]
    assert (a.image - b.image).abs().max() < 1e-3 and (a.image - b.image).abs().mean() < 1e-5
    assert (a.depth - b.depth).abs().max() < 1e-4
    assert (a.weights - b.weights).norm() < 1e-4 * b.weights.norm()
    assert a.means2d.grad is not None and (a.means2d.grad - b.means2d.grad).norm() < 1e-4 * b.means2d.grad.norm()
    assert (ma - mb).norm() < 1e-4 * mb.norm() and (fa - fb).norm() < 1e-4 * fb.norm()


def test_a_zero_quaternion_is_drawn_unrotated_on_the_gsplat_path_as_on_the_others(fresh_gsplat_state, monkeypatch):
    """gsplat's kernels normalise with rsqrt, so a zero quaternion (what the official error-guided sampling gives
    new Gaussians) made its Gaussian NaN and vanish on the GPU path only."""
    fake = _fake_gsplat()
    projection = fake.fully_fused_projection

    def rsqrt_normalising(means, covars, quats, *args, **kwargs):  # as gsplat's CUDA quat_to_rotmat does
        return projection(means, covars, quats * torch.rsqrt((quats * quats).sum(-1, keepdim=True)), *args, **kwargs)

    fake.fully_fused_projection = rsqrt_normalising
    monkeypatch.setattr(gsplat_backend, "_import_gsplat", lambda: fake)
    scene = make_scene(60, 24, 16, seed=5)
    scene.quats[:10] = 0.0
    images = {}
    for backend in ("gsplat", "numba"):
        monkeypatch.setattr(api, "select_backend", lambda requested, device, b=backend: b)
        images[backend] = rasterize(*scene.args(), backend=backend, alpha_max=0.999).image
    assert torch.isfinite(images["gsplat"]).all()
    assert (images["gsplat"] - images["numba"]).abs().max() < 1e-3


def test_no_gaussians_and_a_camera_to_optimise_never_reach_gsplat(fresh_gsplat_state, monkeypatch):
    """gsplat dies on N = 0 (a model's render culls to none at a time far from all its Gaussians), and its
    projection drops K's gradient silently: both go to torch, and gsplat asked for by name refuses K's gradient."""
    monkeypatch.setattr(gsplat_backend, "_import_gsplat", _fake_gsplat)
    empty = make_scene(0, 16, 12)
    background = torch.tensor([0.25, 0.5, 0.75])
    out = rasterize(*empty.args(), background, backend="auto")
    assert out.backend == "torch" and torch.allclose(out.image, background.expand(12, 16, 3))
    scene = make_scene(30, 16, 16)
    args = list(scene.args())
    args[5] = args[5].clone().requires_grad_(True)  # K
    out = rasterize(*args, backend="auto")
    assert out.backend == "torch"
    out.image.sum().backward()
    assert args[5].grad is not None and torch.isfinite(args[5].grad).all()
    with pytest.raises(ValueError, match="no gradient for K"):
        rasterize(*args, backend="gsplat")


def test_gsplat_asked_for_by_name_refuses_float64_instead_of_running_torch_silently(fresh_gsplat_state,
                                                                                     monkeypatch):
    monkeypatch.setattr(gsplat_backend, "_import_gsplat", _fake_gsplat)
    scene = make_scene(30, 16, 16, dtype=torch.float64)
    with pytest.raises(ValueError, match="renders float32 only"):
        rasterize(*scene.args(), backend="gsplat")
    assert rasterize(*scene.args(), backend="auto").backend == "torch"  # auto may choose


def test_gsplat_build_failure_falls_back_to_torch_with_one_warning(fresh_gsplat_state, monkeypatch):
    def broken():
        raise ImportError("gsplat_cuda.so: cannot open shared object file")

    monkeypatch.setattr(gsplat_backend, "_import_gsplat", broken)
    scene = make_scene(30, 16, 16)
    with pytest.warns(RuntimeWarning, match="gsplat's CUDA rasterizer is unavailable.*cannot open shared object"):
        out = rasterize(*scene.args(), backend="gsplat")
    assert out.backend == "torch"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert rasterize(*scene.args(), backend="gsplat").backend == "torch"
    monkeypatch.setattr(api, "select_backend", lambda requested, device: "torch")
    assert torch.equal(out.image, rasterize(*scene.args(), backend="torch").image)


def test_gsplat_warns_once_about_its_fixed_alpha_clamp(fresh_gsplat_state, monkeypatch):
    monkeypatch.setattr(gsplat_backend, "_import_gsplat", _fake_gsplat)
    scene = make_scene(30, 16, 16)
    with pytest.warns(RuntimeWarning, match="clamps alpha at 0.999"):
        rasterize(*scene.args(), alpha_max=0.99)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rasterize(*scene.args(), alpha_max=0.99)  # once


def _layers(opacities, depths, backend):
    """Huge fronto-parallel layers (uniform over the image) at the given depths."""
    n = len(opacities)
    means = torch.tensor([[0.0, 0.0, d] for d in depths])
    out = rasterize(means, torch.tensor([[1.0, 0, 0, 0]] * n), torch.full((n, 3), 1e3), torch.tensor(opacities),
                    torch.ones(n, 1), torch.tensor([[10.0, 0, 4], [0, 10, 3], [0, 0, 1]]), torch.eye(4), 8, 6,
                    backend=backend, return_depth=True, return_weights=True)  # fmt: skip
    return out


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_median_depth_and_weights_on_layers(backend):
    # T: 1 -> 0.7 -> 0.42 -> 0.21: crosses 0.5 at the second layer (depth 3), whatever the input order.
    out = _layers([0.4, 0.3, 0.5], [3.0, 2.0, 4.0], backend)
    assert torch.allclose(out.depth, torch.full((6, 8), 3.0))
    assert torch.allclose(out.alpha, torch.full((6, 8), 1 - 0.7 * 0.6 * 0.5))
    # weights: alpha_i * T_i summed over the 48 pixels.
    assert torch.allclose(out.weights, 48 * torch.tensor([0.4 * 0.7, 0.3, 0.5 * 0.42]), rtol=1e-5)
    # Never below 0.5: 0.
    out = _layers([0.2, 0.3], [2.0, 3.0], backend)
    assert torch.all(out.depth == 0)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_weights_sum_to_accumulated_alpha(backend):
    # Per pixel sum_j alpha_j T_j = 1 - T_final, so the per-Gaussian weights sum to the alpha image's sum.
    scene = make_scene(600, 40, 30, seed=9)
    out = rasterize(*scene.args(), backend=backend, return_weights=True)
    assert out.weights.shape == (600,) and bool((out.weights >= 0).all())
    assert out.weights.sum().item() == pytest.approx(out.alpha.sum().item(), rel=1e-5)
    assert torch.all(out.weights[~out.visible] == 0)


def test_means2d_grad_ndc_norm_scales_by_half_image_size():
    scene = make_scene(200, 40, 24, seed=6).leaves()
    out = rasterize(*scene.args())
    assert torch.all(out.means2d_grad_ndc_norm() == 0)  # before any backward
    out.image.sum().backward()
    g = out.means2d.grad
    expected = torch.sqrt((g[:, 0] * 20.0) ** 2 + (g[:, 1] * 12.0) ** 2) * out.visible
    assert torch.allclose(out.means2d_grad_ndc_norm(), expected)
    assert out.means2d_grad_ndc_norm()[out.visible].gt(0).float().mean() > 0.5


def test_numba_backward_uses_the_colours_of_its_forward_though_the_caller_changes_them_after(monkeypatch):
    """The numba forward kept a view of the caller's features for the backward: changed in place in between
    (autograd's version check does not see numpy views), the gradients came from the new values."""
    monkeypatch.setattr(api, "select_backend", lambda requested, device: "numba")
    scene = make_scene(80, 24, 16, seed=6)
    grads = []
    for change_after_forward in (False, True):
        s = scene.leaves()
        out = rasterize(*s.args(), backend="numba")
        if change_after_forward:
            with torch.no_grad():
                s.features.mul_(2.0)
        out.image.sum().backward()
        grads.append(s.opacities.grad.clone())
    assert torch.equal(grads[0], grads[1])


def test_auto_renders_a_camera_to_optimise_with_the_backend_that_differentiates_it():
    """On CPU, 'auto' chose numba, which refuses a K or viewmat that requires grad; numba by name still refuses."""
    scene = make_scene(30, 16, 16)
    for index in (5, 6):  # K, viewmat
        args = list(scene.args())
        args[index] = args[index].clone().requires_grad_(True)
        out = rasterize(*args, backend="auto")
        assert out.backend == "torch"
        out.image.sum().backward()
        assert args[index].grad is not None and torch.isfinite(args[index].grad).all()
        with pytest.raises(ValueError, match="no gradient for K or viewmat"):
            rasterize(*args, backend="numba")
