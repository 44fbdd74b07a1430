"""PSNR / SSIM against independent implementations: scikit-image and a plain 2-D-window transcription of
the 3DGS formula."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from stgc.metrics import lpips_status, psnr, psnr_of_mse, psnr_per_image, ssim, ssim_map, ssim_per_image


def _pair(seed: int, h: int = 37, w: int = 45, c: int = 3) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    ref = rng.random((h, w, c))
    # A correlated, clipped distortion so SSIM sits well away from 0 and 1.
    img = np.clip(ref + 0.15 * rng.standard_normal((h, w, c)), 0.0, 1.0)
    return img, ref


def _ssim_3dgs_2d_window(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """The 3DGS loss_utils definition written out directly: a full 11x11 window, one grouped conv per moment."""
    x, y = img.permute(2, 0, 1)[None], ref.permute(2, 0, 1)[None]
    c = x.shape[1]
    g = torch.tensor([np.exp(-((i - 5) ** 2) / (2 * 1.5**2)) for i in range(11)], dtype=x.dtype)
    g = g / g.sum()
    window = (g[:, None] @ g[None, :]).expand(c, 1, 11, 11).contiguous()

    def conv(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, window, padding=5, groups=c)

    mu1, mu2 = conv(x), conv(y)
    s11 = conv(x * x) - mu1**2
    s22 = conv(y * y) - mu2**2
    s12 = conv(x * y) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s11 + s22 + c2))
    return m


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_psnr_matches_skimage(seed: int) -> None:
    img, ref = _pair(seed)
    ours = float(psnr(torch.from_numpy(img), torch.from_numpy(ref)))
    assert ours == pytest.approx(peak_signal_noise_ratio(ref, img, data_range=1.0), abs=1e-9)


def test_psnr_uint8_and_per_image() -> None:
    img, ref = _pair(3)
    img8, ref8 = (img * 255).round().astype(np.uint8), (ref * 255).round().astype(np.uint8)
    expected = peak_signal_noise_ratio(ref8, img8, data_range=255)
    assert float(psnr(img8, ref8)) == pytest.approx(expected, abs=1e-4)
    batch_img = torch.from_numpy(np.stack([img, ref])).permute(0, 3, 1, 2)
    batch_ref = torch.from_numpy(np.stack([ref, ref])).permute(0, 3, 1, 2)
    per = psnr_per_image(batch_img, batch_ref)
    assert float(per[0]) == pytest.approx(peak_signal_noise_ratio(ref, img, data_range=1.0), abs=1e-9)
    assert torch.isinf(per[1])


@pytest.mark.parametrize("seed", [0, 1])
def test_ssim_interior_equals_skimage(seed: int) -> None:
    """Same window, constants and population statistics: on pixels whose window stays inside the image the
    two maps are identical; skimage's mean is exactly the interior mean (it crops 5 px per side)."""
    img, ref = _pair(seed)
    sk_mean, sk_map = structural_similarity(
        ref, img, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0,
        channel_axis=-1, full=True,
    )
    ours = ssim_map(torch.from_numpy(img), torch.from_numpy(ref))[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(ours[5:-5, 5:-5], sk_map[5:-5, 5:-5], atol=1e-10)
    assert ours[5:-5, 5:-5].mean() == pytest.approx(sk_mean, abs=1e-10)
    # The documented difference: 3DGS also averages the zero-padded border (here it raises the mean).
    whole = float(ssim(torch.from_numpy(img), torch.from_numpy(ref)))
    assert whole != pytest.approx(sk_mean, abs=1e-4)


def test_ssim_whole_image_equals_3dgs_formula() -> None:
    img, ref = _pair(5, h=23, w=31)
    a, b = torch.from_numpy(img), torch.from_numpy(ref)
    expected = _ssim_3dgs_2d_window(a, b)
    ours = ssim_map(a, b)
    torch.testing.assert_close(ours, expected, atol=1e-12, rtol=0)
    assert float(ssim(a, b)) == pytest.approx(float(expected.mean()), abs=1e-12)


def test_ssim_layouts_agree_and_identity() -> None:
    img, ref = _pair(6, h=20, w=24)
    a, b = torch.from_numpy(img), torch.from_numpy(ref)
    hwc = float(ssim(a, b))
    bchw = ssim_per_image(a.permute(2, 0, 1)[None].repeat(2, 1, 1, 1), b.permute(2, 0, 1)[None].repeat(2, 1, 1, 1))
    assert torch.allclose(bchw, torch.full((2,), hwc, dtype=torch.float64))
    assert float(ssim(b, b)) == pytest.approx(1.0, abs=1e-12)
    gray = float(ssim(a[..., 0], b[..., 0]))
    assert gray == pytest.approx(float(ssim_map(a, b)[0, 0].mean()), abs=1e-12)


def test_ssim_gradient_matches_finite_differences() -> None:
    img, ref = _pair(7, h=12, w=13, c=2)
    x = torch.from_numpy(img).requires_grad_(True)
    # fast_mode checks a random directional derivative: the same test, a few dozen times cheaper.
    assert torch.autograd.gradcheck(
        lambda t: ssim(t, torch.from_numpy(ref)), (x,), eps=1e-6, atol=1e-6, fast_mode=True)


@pytest.mark.parametrize("layout", ["hw", "hwc", "bchw"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_ssim_fused_backward_equals_autograd_through_the_map(layout: str, dtype: torch.dtype) -> None:
    """ssim() on the CPU runs a hand-written backward; ssim_map().mean() is plain autograd through the same math."""
    img, ref = _pair(8, h=19, w=26)
    a, b = torch.from_numpy(img).to(dtype), torch.from_numpy(ref).to(dtype)
    if layout == "hw":
        a, b = a[..., 1], b[..., 1]
    elif layout == "bchw":
        a, b = torch.stack([a, b.flip(0)]).permute(0, 3, 1, 2), torch.stack([b, a.flip(0)]).permute(0, 3, 1, 2)
    fused_in, map_in = a.clone().requires_grad_(True), a.clone().requires_grad_(True)
    fused, generic = ssim(fused_in, b), ssim_map(map_in, b).mean()
    fused.backward()
    generic.backward()
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    assert float(fused.detach()) == pytest.approx(float(generic.detach()), abs=tol)
    assert fused_in.grad is not None and map_in.grad is not None
    assert float((fused_in.grad - map_in.grad).abs().max()) <= tol * float(map_in.grad.abs().max()) * 10


def test_ssim_reference_that_needs_a_gradient_gets_one() -> None:
    img, ref = _pair(9, h=14, w=15)
    x = torch.from_numpy(img).requires_grad_(True)
    y = torch.from_numpy(ref).requires_grad_(True)
    ssim(x, y).backward()
    assert x.grad is not None and y.grad is not None and float(y.grad.abs().sum()) > 0


def test_shape_mismatch_is_reported() -> None:
    with pytest.raises(ValueError, match="shapes differ"):
        ssim(torch.zeros(8, 8, 3), torch.zeros(8, 9, 3))


def test_lpips_reports_why_it_is_unavailable_at_each_missing_piece(monkeypatch, tmp_path) -> None:
    import importlib.util
    from types import SimpleNamespace

    from stgc.metrics import image as metrics

    bad, why = lpips_status("squeezenet-nope")
    assert not bad and "unknown LPIPS network" in why
    # A fake lpips package (with or without its linear weights) and a fake torch hub cache, whatever is installed.
    package = tmp_path / "lpips"
    installed = {"lpips": SimpleNamespace(origin=str(package / "__init__.py")), "torchvision": SimpleNamespace()}
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: installed.get(name))
    monkeypatch.setattr(metrics, "_torch_hub_checkpoints", lambda: tmp_path / "hub")
    del installed["torchvision"]
    assert lpips_status("alex") == (False, "skipped: python package 'torchvision' is not installed")
    installed["torchvision"] = SimpleNamespace()
    ok, why = lpips_status("alex")
    assert not ok and why.startswith("skipped: lpips linear weights missing")
    (package / "weights" / "v0.1").mkdir(parents=True)
    (package / "weights" / "v0.1" / "alex.pth").write_bytes(b"w")
    ok, why = lpips_status("alex")
    assert not ok and "backbone weights not in the torch hub cache" in why and "not downloading" in why
    (tmp_path / "hub").mkdir()
    (tmp_path / "hub" / "alexnet-owt-7be5be79.pth").write_bytes(b"w")
    assert lpips_status("alex") == (True, "available")


def _bt709_yuv420_10bit(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """BT.709 limited-range 10-bit 4:2:0 written out from the standard (ITU-R BT.709-6, items 3.2-3.5), as a
    second implementation: E'Y = 0.2126 R + 0.7152 G + 0.0722 B; E'CB = (B - Y) / 1.8556; E'CR = (R - Y) / 1.5748;
    D'Y = round((219 E'Y + 16) 4), D'C = round((224 E'C + 128) 4); chroma is the mean of each 2x2 block."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    y = 0.2126 * r + 0.7152 * g + 0.0722 * b
    cb = (b - y) / 1.8556
    cr = (r - y) / 1.5748
    h, w = y.shape
    cb = cb.reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))
    cr = cr.reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))
    return np.rint((219 * y + 16) * 4), np.rint((224 * cb + 128) * 4), np.rint((224 * cr + 128) * 4)


def test_yuv_psnr_matches_bt709_written_out_and_weights_6_1_1():
    from stgc.metrics import yuv_psnr

    rng = np.random.default_rng(3)
    ref = rng.uniform(0.05, 0.95, size=(24, 32, 3))
    img = np.clip(ref + rng.normal(0, 0.03, size=ref.shape), 0, 1)
    got = yuv_psnr(torch.from_numpy(img), ref)
    expected = {}
    for name, a, b in zip("yuv", _bt709_yuv420_10bit(img), _bt709_yuv420_10bit(ref)):
        expected[name] = 10 * np.log10(1023.0**2 / np.mean((a - b) ** 2))
    for name in "yuv":
        assert got[name] == pytest.approx(expected[name], abs=1e-9)
    assert got["yuv"] == pytest.approx((6 * got["y"] + got["u"] + got["v"]) / 8)
    assert got["u"] != pytest.approx(got["y"], abs=0.5)  # the planes are scored apart
    same = yuv_psnr(ref, ref)
    assert all(np.isinf(v) for v in same.values())


def test_an_exact_chroma_plane_counts_at_the_ceiling_in_the_yuv_combination():
    """Grey content has exact U and V: the combination was +inf (then 100 dB in the means), hiding the luma's error."""
    from stgc.metrics import yuv_psnr
    from stgc.metrics.image import PSNR_CEILING_DB

    rng = np.random.default_rng(0)
    grey = np.repeat(rng.uniform(0.1, 0.9, size=(16, 16, 1)), 3, axis=2)
    noisy = np.repeat(np.clip(grey[..., :1] + rng.normal(0, 0.02, size=(16, 16, 1)), 0, 1), 3, axis=2)
    scores = yuv_psnr(noisy, grey)
    assert math.isinf(scores["u"]) and math.isinf(scores["v"]) and math.isfinite(scores["y"])
    assert scores["yuv"] == pytest.approx((6 * scores["y"] + 2 * PSNR_CEILING_DB) / 8)
    assert math.isinf(yuv_psnr(grey, grey)["yuv"])  # a wholly exact picture stays exact


def test_psnr_of_an_error_is_the_images_psnr():
    gen = torch.Generator().manual_seed(5)
    img, ref = torch.rand(3, 8, 8, generator=gen), torch.rand(3, 8, 8, generator=gen)
    error = float(((img - ref) ** 2).mean())
    assert psnr_of_mse(error) == pytest.approx(float(psnr(img, ref)), abs=1e-4)
    assert psnr_of_mse(error * 255 ** 2, 255.0) == pytest.approx(psnr_of_mse(error), abs=1e-9)
    assert psnr_of_mse(0.01) == pytest.approx(20.0) and psnr_of_mse(0.0) == float("inf")
    assert math.isnan(psnr_of_mse(-1.0)) and math.isnan(psnr_of_mse(float("nan")))


def test_an_lpips_record_names_the_input_range_that_scored_it(monkeypatch) -> None:
    """LPIPS of [0, 1] images fed directly (3DGS/STG's scripts) and mapped to [-1, 1] (the lpips package) differ by
    more than methods do: the record's note says which one scored it."""
    from stgc.metrics import image

    monkeypatch.setattr(image, "lpips_status", lambda net: (True, "available"))
    monkeypatch.setattr(image.LPIPS, "__init__", lambda self, net="alex", rescale=True: None)
    assert image.LPIPS.create("alex")[1] == "LPIPS-alex, images [0, 1] mapped to [-1, 1] as the lpips package expects"
    assert "fed directly, as the 3DGS/STG" in image.LPIPS.create("vgg", rescale=False)[1]
