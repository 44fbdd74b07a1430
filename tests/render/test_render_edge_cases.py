"""Defined behaviour at the edges: empty scenes, nothing visible, degenerate sizes and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from stgc.render import numba_backend, rasterize

from .scenes import make_scene

BACKENDS = ["numba", "torch"]


def _single(mean, scale, opacity, color, width=16, height=12, focal=20.0):
    """One Gaussian, identity camera at the origin looking down +z, principal point at the image centre."""
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    means = torch.tensor([mean], dtype=torch.float32)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    scales = torch.full((1, 3), float(scale))
    return means, quats, scales, torch.tensor([float(opacity)]), torch.tensor([color], dtype=torch.float32), K, \
        torch.eye(4), width, height  # fmt: skip


def _grad_inputs(args):
    return [a.clone().requires_grad_(True) for a in args[:5]] + list(args[5:])


@pytest.mark.parametrize("backend", BACKENDS)
def test_no_gaussians_gives_background(backend):
    bg = torch.tensor([0.1, 0.2, 0.3], requires_grad=True)
    empty = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)]
    params = [t.requires_grad_(True) for t in empty]
    out = rasterize(*params, torch.eye(3) * 10, torch.eye(4), 7, 5, bg, backend=backend)
    assert out.image.shape == (5, 7, 3) and out.radii.shape == (0, 2) and out.visible.shape == (0,)
    assert torch.allclose(out.image, bg.detach().expand(5, 7, 3))
    assert torch.all(out.alpha == 0)
    out.image.sum().backward()
    assert all(p.grad is not None and p.grad.numel() == 0 for p in params)
    assert torch.allclose(bg.grad, torch.full((3,), 35.0))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("where", ["behind", "on_camera", "offscreen", "zero_opacity"])
def test_nothing_visible_gives_background_and_zero_grads(backend, where):
    scene = make_scene(50, 24, 16, seed=2, rotate_camera=False)
    if where == "behind":
        scene.means[:, 2] = -scene.means[:, 2]
    elif where == "on_camera":
        scene.means[:, 2] = 0.0  # exactly in the camera plane: must be culled without inf/NaN
    elif where == "offscreen":
        scene.means[:, 0] += 1000.0
    else:
        scene.opacities.zero_()
    s = scene.leaves()
    bg = torch.tensor([0.3, 0.6, 0.9], requires_grad=True)
    out = rasterize(*s.args(), bg, backend=backend, return_depth=True, return_weights=True)
    assert not out.visible.any() and out.num_intersections == 0
    assert torch.equal(out.image, bg.detach().expand(16, 24, 3))
    assert torch.all(out.depth == 0) and torch.all(out.weights == 0)
    (out.image.sum() + out.alpha.sum()).backward()
    for p in s.params():
        assert torch.all(p.grad == 0), where
    assert torch.all(out.means2d_grad_ndc_norm() == 0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_huge_gaussian_is_a_uniform_layer(backend):
    # Footprint >> image (sigma = 4e6 px): sigma ~ 0 at every pixel, so every pixel is o*c + (1-o)*bg.
    args = _grad_inputs(_single([0.0, 0.0, 5.0], scale=1e6, opacity=0.6, color=[1.0, 0.5, 0.0]))
    bg = torch.tensor([0.0, 0.0, 1.0])
    out = rasterize(*args, bg, backend=backend)
    expected = 0.6 * torch.tensor([1.0, 0.5, 0.0]) + 0.4 * bg
    assert torch.allclose(out.image, expected.expand(12, 16, 3), atol=1e-5)
    # Radius = ceil(sqrt(2 ln(255 * 0.6)) * 4e6) px, still a valid int32.
    assert out.radii[0, 0].item() == pytest.approx(math.sqrt(2 * math.log(255 * 0.6)) * 4e6, rel=1e-5)
    (out.image * torch.tensor([1.0, 2.0, 3.0])).sum().backward()
    assert all(torch.isfinite(a.grad).all() for a in args[:5])
    assert args[3].grad.item() == pytest.approx(192 * (1.0 + 1.0 - 3.0), rel=1e-4)  # d/do of sum(w * (o c + (1-o) bg))


@pytest.mark.parametrize("backend", BACKENDS)
def test_tiny_gaussian_is_the_dilation_kernel(backend):
    # A point-like Gaussian is the 0.3 px^2 screen-space dilation (eps2d): alpha = o exp(-d^2 / (2 * 0.3)).
    # Mean on the centre of pixel (8, 6): K maps (0, 0, z) to (8, 6); pixel centres are at +0.5, so shift by 0.5 px.
    focal, z = 20.0, 5.0
    args = list(_single([0.5 * z / focal, 0.5 * z / focal, z], scale=1e-7, opacity=0.9, color=[1.0, 1.0, 1.0]))
    args = _grad_inputs(args)
    out = rasterize(*args, backend=backend)
    img = out.image[..., 0].detach()
    assert img[6, 8].item() == pytest.approx(0.9, rel=1e-5)
    assert img[6, 9].item() == pytest.approx(0.9 * math.exp(-1 / 0.6), rel=1e-4)
    assert img[7, 9].item() == pytest.approx(0.9 * math.exp(-2 / 0.6), rel=1e-4)
    # Two pixels away alpha = 0.9 exp(-4/0.6) = 1.1e-3 < 1/255: skipped.
    assert img[6, 10].item() == 0.0
    out.image.sum().backward()
    assert all(torch.isfinite(a.grad).all() for a in args[:5])


@pytest.mark.parametrize("backend", BACKENDS)
def test_one_pixel_image(backend):
    args = _grad_inputs(_single([0.0, 0.0, 4.0], scale=0.5, opacity=0.5, color=[0.2, 0.4, 0.6], width=1, height=1))
    out = rasterize(*args, backend=backend)
    assert out.image.shape == (1, 1, 3)
    # Mean exactly on the single pixel centre; the footprint is wide so sigma ~ 0: alpha ~ 0.5.
    assert torch.allclose(out.image[0, 0], torch.tensor([0.1, 0.2, 0.3]), atol=1e-3)
    out.image.sum().backward()
    assert args[4].grad[0, 0].item() == pytest.approx(out.alpha.item(), rel=1e-6)


@pytest.mark.parametrize("channels", [1, 32])
def test_channel_counts_agree_between_backends(channels):
    scene = make_scene(300, 40, 24, channels=channels, seed=channels)
    outs = {}
    for backend in BACKENDS:
        s = scene.leaves()
        out = rasterize(*s.args(), backend=backend)
        out.image.pow(2).sum().backward()
        outs[backend] = (out.image.detach(), s.features.grad, s.means.grad)
    assert outs["numba"][0].shape == (24, 40, channels)
    for x, y in zip(outs["numba"], outs["torch"]):
        assert (x - y).abs().max() <= 1e-5 * max(1.0, y.abs().max().item())


ARG_NAMES = ["means", "quats", "scales", "opacities", "features", "K", "viewmat"]


@pytest.mark.parametrize("name", ARG_NAMES + ["background"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_input_is_rejected_by_name(name, bad):
    scene = make_scene(5, 8, 8)
    args = dict(zip(ARG_NAMES, [scene.means, scene.quats, scene.scales, scene.opacities, scene.features, scene.K,
                                scene.viewmat]))  # fmt: skip
    args["background"] = torch.zeros(3)
    args[name] = args[name].clone()
    args[name].view(-1)[0] = bad
    with pytest.raises(ValueError, match=f"^{name}: contains NaN or inf"):
        rasterize(**args, width=8, height=8)


@pytest.mark.parametrize(
    "name,value,message",
    [
        ("means", torch.zeros(5, 2), "means: expected shape"),
        ("quats", torch.zeros(4, 4), "quats: expected shape"),
        ("scales", torch.zeros(5), "scales: expected shape"),
        ("opacities", torch.zeros(5, 1), "opacities: expected shape"),
        ("features", torch.zeros(5, 0), "features: need at least one channel"),
        ("K", torch.eye(4), "K: expected shape"),
        ("viewmat", torch.eye(3), "viewmat: expected shape"),
        ("background", torch.zeros(4), "background: expected shape"),
        ("width", 0, "width: expected a positive integer"),
        ("height", 2.5, "height: expected a positive integer"),
        ("backend", "cuda", "backend must be one of"),
        ("alpha_max", 1.0, "alpha_max"),
        ("K", torch.tensor([[0.0, 0, 4], [0, 10, 4], [0, 0, 1]]), "K: focal lengths must be positive"),
        ("near_plane", 0.0, "near_plane: expected a positive"),
        ("eps2d", -0.1, "eps2d: expected a finite value >= 0"),
    ],
)
def test_bad_arguments_raise_value_error(name, value, message):
    scene = make_scene(5, 8, 8)
    kwargs = dict(means=scene.means, quats=scene.quats, scales=scene.scales, opacities=scene.opacities,
                  features=scene.features, K=scene.K, viewmat=scene.viewmat, width=8, height=8)  # fmt: skip
    kwargs[name] = value
    with pytest.raises(ValueError, match=message):
        rasterize(**kwargs)


def test_numpy_inputs_are_accepted():
    scene = make_scene(20, 16, 16)
    arrays = [t.numpy() for t in scene.args()[:7]]
    out = rasterize(*arrays, 16, 16)
    ref = rasterize(*scene.args())
    assert torch.equal(out.image, ref.image)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_depth_order_is_the_stable_depth_sort_of_the_gaussians_with_a_tile(dtype):
    rng = np.random.default_rng(0)
    depths = rng.choice(np.array([0.5, 1.0, 1.0 + 1e-6, 2.0, 1e-30, 3.5e4]), size=400).astype(dtype)  # many ties
    radii = rng.integers(0, 3, size=(400, 2)).astype(np.int32)
    culled = (radii == 0).all(axis=1)
    depths[culled] = rng.choice([-1.0, 0.0, 0.7], size=int(culled.sum()))  # culled: behind the camera or anywhere
    want = [i for i in torch.argsort(torch.from_numpy(depths), stable=True).tolist() if not culled[i]]
    assert 0 < int(culled.sum()) < 400
    assert numba_backend.depth_order(depths, radii).tolist() == want


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_depth_order_sorts_depths_over_every_bit_of_the_key(dtype):
    # Depths from 1e-30 to 1e30: every radix pass of the key (3 for float32, 6 for float64) decides some order.
    rng = np.random.default_rng(1)
    depths = (10.0 ** rng.uniform(-30, 30, size=5000)).astype(dtype)
    depths[::7] = depths[3]  # ties keep id order
    radii = np.ones((5000, 2), dtype=np.int32)
    want = torch.argsort(torch.from_numpy(depths), stable=True).numpy()
    assert np.array_equal(numba_backend.depth_order(depths, radii), want)


@pytest.mark.parametrize("threads", [1, 2])
def test_numba_tile_lists_are_the_torch_binning_less_the_tiles_a_gaussian_cannot_reach(threads):
    """bin_tiles (numba; its counting sort by tile runs over one run of the depth order per thread, and each box
    row keeps the run of tiles between the first and the last one reached) against bin_tiles_torch (a
    sort of (tile, depth rank) keys): every tile's list is the torch list, in the same order, without the Gaussians
    whose alpha >= 1/255 ellipse misses the tile (_reaches_tile, exact)."""
    import numba

    from stgc.render import _numba_kernels as kernels
    from stgc.render.projection import ALPHA_MIN, SIGMA_CUT_MARGIN, bin_tiles_torch, tile_grid, tile_rects

    if threads > numba.config.NUMBA_NUM_THREADS:
        pytest.skip("needs two numba threads")
    width, height, tile = 70, 45, 8
    scene = make_scene(2000, width, height, channels=3, sigma_px=(0.5, 12.0), seed=4)
    means, quats, scales, opacities = scene.params()[:4]
    proj = numba_backend.project_numba(means, quats, scales, opacities, scene.K, scene.viewmat, width, height,
                                       eps2d=0.3, near_plane=0.01)
    gdata = numba_backend._pack(proj.means2d, proj.conics, opacities, proj.depths, np.float32)
    # The sigma above which o exp(-sigma) < 1/255 for certain (what binning tests tiles against), in numpy
    o = opacities.numpy().astype(np.float64)
    want_cut = np.log(np.maximum(o, ALPHA_MIN) * 255.0) + SIGMA_CUT_MARGIN
    np.testing.assert_allclose(gdata[:, 6], want_cut, rtol=1e-6)
    assert np.array_equal(gdata[:, [0, 1, 2, 3, 4, 5, 7]],
                          np.column_stack([proj.means2d.numpy(), proj.conics.numpy(), opacities.numpy(),
                                           proj.depths.numpy()]))
    radii = proj.radii.numpy()
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(threads)
        offsets, flat = kernels.bin_tiles(gdata, radii, numba_backend.depth_order(proj.depths.numpy(), radii),
                                          width, height, tile, numba.get_num_threads())
    finally:
        numba.set_num_threads(before)
    want_offsets, want_flat = bin_tiles_torch(tile_rects(proj.radii, proj.means2d, width, height, tile), proj.depths,
                                              proj.visible, width, height, tile)
    tiles_x, tiles_y = tile_grid(width, height, tile)
    assert offsets.shape[0] == tiles_x * tiles_y + 1 and flat.shape[0] == offsets[-1] > 5000
    m2d, conic = proj.means2d.numpy(), proj.conics.numpy()
    alpha_floor = np.log(np.float32(255.0) * opacities.numpy().astype(np.float32))
    dropped = 0
    for t in range(tiles_x * tiles_y):
        x0, y0 = (t % tiles_x) * tile, (t // tiles_x) * tile
        x1, y1 = min(x0 + tile, width) - 0.5, min(y0 + tile, height) - 0.5
        candidates = want_flat[want_offsets[t]:want_offsets[t + 1]].tolist()
        want = [g for g in candidates if kernels._reaches_tile(gdata, g, x0 + 0.5, x1, y0 + 0.5, y1)]
        dropped += len(candidates) - len(want)
        assert flat[offsets[t]:offsets[t + 1]].tolist() == want, t
        # Independently: a dropped Gaussian's alpha, as the compositor evaluates it in float32, is below 1/255 at
        # every pixel centre of the tile.
        gone = np.array(sorted(set(candidates) - set(want)), dtype=np.int64)
        if gone.size:
            px, py = np.meshgrid(np.arange(x0 + 0.5, x1 + 0.5, dtype=np.float32),
                                 np.arange(y0 + 0.5, y1 + 0.5, dtype=np.float32))
            dx = m2d[gone, 0, None] - px.reshape(1, -1)
            dy = m2d[gone, 1, None] - py.reshape(1, -1)
            a, b, c = (conic[gone, k, None] for k in range(3))
            sigma = np.float32(0.5) * (a * dx * dx + c * dy * dy) + b * dx * dy
            assert (sigma > alpha_floor[gone, None]).all(), t
    assert dropped > 0  # the ellipse test did cull some box tiles


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_near_plane_and_eps2d_given_are_the_ones_used(backend):
    # Two Gaussians at depths 0.15 and 0.25 in front of the camera: a near plane of 0.2 culls the first only; and
    # eps2d is the footprint's added variance (its radius grows with it).
    means = torch.tensor([[0.0, 0.0, 0.15], [0.0, 0.0, 0.25]])
    args = (means, torch.tensor([[1.0, 0, 0, 0]] * 2), torch.full((2, 3), 1e-4), torch.tensor([0.9, 0.9]),
            torch.ones(2, 3), torch.tensor([[20.0, 0, 8], [0, 20, 6], [0, 0, 1]]), torch.eye(4), 16, 12)
    assert rasterize(*args, backend=backend, near_plane=0.1).visible.tolist() == [True, True]
    assert rasterize(*args, backend=backend, near_plane=0.2).visible.tolist() == [False, True]
    small, large = (rasterize(*args, backend=backend, eps2d=e).radii[1, 0].item() for e in (0.3, 3.0))
    assert large > small  # sqrt(2 ln(255 x 0.9)) x sqrt(eps2d + ~0): 2 px, then 6


@pytest.mark.parametrize("backend", BACKENDS)
def test_with_eps2d_zero_a_gaussian_far_below_a_pixel_is_culled_not_drawn_as_a_square(backend):
    # Its 2-D determinant is below the clamp that keeps the conic finite; drawn, the clamped conic painted every
    # pixel of its tiles at full opacity (and differently per backend, their tiles differing).
    out = rasterize(*_single([0.0, 0.0, 5.0], 1e-7, 0.9, [1.0, 1.0, 1.0], width=32, height=32), backend=backend,
                    eps2d=0.0)
    assert not out.visible.any() and out.alpha.max().item() == 0.0


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_footprint_beyond_every_bound_is_capped_and_renders_finite(backend):
    # float64: a radius beyond 2^63 pixels wrapped to a negative int64 in numba (the Gaussian vanished) while torch
    # capped it. float32, rotated: the covariance overflows to a non-finite conic; the Gaussian is culled and the
    # image stays the background (0 x NaN made it NaN in the torch backend).
    huge = list(_single([0.0, 0.0, 5.0], 1e18, 0.6, [1.0, 1.0, 1.0]))
    huge[:5] = [a.double() for a in huge[:5]]
    huge[5] = huge[5].double()
    out = rasterize(*huge, backend=backend)
    assert out.radii.min().item() > 2**29 and out.image.isfinite().all()
    overflow = list(_single([0.0, 0.0, 5.0], 1e17, 0.6, [1.0, 1.0, 1.0]))
    overflow[1] = torch.tensor([[0.8, 0.3, 0.4, 0.33]])
    overflow[0].requires_grad_(True)
    out = rasterize(*overflow, backend=backend)
    assert out.image.isfinite().all()
    out.image.sum().backward()  # numba's gradient stays finite; torch's autograd through the overflow is NaN
    assert overflow[0].grad is not None and (backend == "torch" or overflow[0].grad.isfinite().all())


def test_interleaved_tiles_is_a_permutation_that_deals_every_thread_tiles_from_all_over_the_image():
    from stgc.render import _numba_kernels as kernels

    assert kernels.interleaved_tiles(10, 3).tolist() == [0, 3, 6, 9, 1, 4, 7, 2, 5, 8]
    for n_tiles, n_threads in ((920, 2), (1024, 2), (7, 4), (3, 8), (1, 1), (0, 2)):
        order = kernels.interleaved_tiles(n_tiles, n_threads)
        assert sorted(order.tolist()) == list(range(n_tiles)) and order.dtype == np.int64
    # numba's static schedule gives thread t the t-th contiguous block of the loop: with 2 threads over 920 tiles
    # (a 320x180 image in 40 x 23 tiles of 8), each block holds every row of tiles, half of each.
    first_block = kernels.interleaved_tiles(920, 2)[:460]
    assert len(set((first_block // 40).tolist())) == 23


def test_reaches_tile_never_drops_a_pixel_for_conics_rounded_to_a_c_at_most_b_squared():
    """_reaches_tile against a brute force over every pixel centre of the rectangle, for conics that float32 left
    without a c > b^2 (not strictly convex; the edges that face the mean still suffice) and for ordinary ones. The
    compositor uses a pixel whenever o exp(-sigma) >= 1/255, i.e. sigma <= the cutoff: such a pixel must never be
    missed. It may answer True for a rectangle without one (conservative), which the counts below bound."""
    from stgc.render import _numba_kernels as kernels

    rng = np.random.default_rng(11)
    outcomes = {"degenerate": [0, 0], "ordinary": [0, 0]}  # [reached, missed] with the mean outside the rectangle
    for trial in range(3000):
        degenerate = trial % 2 == 0
        a, c = (np.float32(v) for v in rng.uniform(0.005, 0.5, 2))
        root = np.sqrt(np.float64(a) * np.float64(c))
        # degenerate: |b| at or just above sqrt(a c), so that a c <= b^2 in float32; ordinary: well inside
        b = np.float32(rng.choice([-1, 1]) * root * (rng.uniform(1.0, 1.001) if degenerate else rng.uniform(0, 0.9)))
        if degenerate:
            assert not a * c > b * b
        cut = np.float32(rng.uniform(0.5, 5.5))
        mean = rng.uniform(-20, 60, 2).astype(np.float32)
        x0, y0 = (int(v) for v in rng.integers(0, 40, 2))
        width, height = (int(v) for v in rng.integers(1, 9, 2))
        gdata = np.zeros((1, 8), np.float32)
        gdata[0, :7] = [mean[0], mean[1], a, b, c, 1.0, cut]
        px, py = np.meshgrid(np.arange(x0, x0 + width, dtype=np.float32) + np.float32(0.5),
                             np.arange(y0, y0 + height, dtype=np.float32) + np.float32(0.5))
        dx, dy = mean[0] - px, mean[1] - py
        sigma = np.float32(0.5) * (a * dx * dx + c * dy * dy) + b * dx * dy
        some_pixel = bool((sigma <= cut).any())
        reaches = kernels._reaches_tile(gdata, 0, x0 + 0.5, x0 + width - 0.5, y0 + 0.5, y0 + height - 0.5)
        assert reaches or not some_pixel, (trial, a, b, c, cut, mean, x0, y0, width, height)
        inside = x0 <= mean[0] <= x0 + width and y0 <= mean[1] <= y0 + height
        if not inside:
            outcomes["degenerate" if degenerate else "ordinary"][0 if some_pixel else 1] += 1
    # Both kinds met rectangles they reach from outside and rectangles they miss: the test saw both answers.
    assert all(reached > 20 and missed > 20 for reached, missed in outcomes.values()), outcomes
