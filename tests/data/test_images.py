"""Image decoding, resampling and the bounded cache."""

from __future__ import annotations

import numpy as np
from PIL import Image

from stgc.data.images import ImageCache, read_image, resize_image


def test_cache_is_bounded_and_least_recently_used():
    cache = ImageCache(max_bytes=3 * 100)
    loads = []
    make = lambda k: (lambda: (loads.append(k), np.full(100, k, np.uint8))[1])
    for k in (1, 2, 3):
        cache.get(k, make(k))
    cache.get(1, make(1))  # hit: 1 becomes most recent
    cache.get(4, make(4))  # evicts 2, the least recently used
    assert loads == [1, 2, 3, 4] and cache.bytes == 300 and len(cache) == 3
    cache.get(2, make(2))
    assert loads[-1] == 2 and cache.peek(3) is None and cache.peek(1) is not None
    assert cache.hits == 1 and cache.misses == 5


def test_box_downscale_is_the_block_mean_and_lanczos_otherwise():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, size=(12, 16, 3), dtype=np.uint8)
    small = resize_image(image, 4, 3)
    expected = image.reshape(3, 4, 4, 4, 3).astype(float).mean(axis=(1, 3))
    assert np.abs(small - expected).max() <= 0.5
    odd = resize_image(image, 10, 7)
    assert odd.shape == (7, 10, 3) and odd.dtype == np.uint8


def test_read_image_modes(tmp_path):
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    Image.fromarray(grey).save(tmp_path / "g.png")
    assert np.array_equal(read_image(tmp_path / "g.png"), np.repeat(grey[..., None], 3, -1))
    deep = (np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000)
    Image.fromarray(deep).save(tmp_path / "d.png")
    assert np.array_equal(read_image(tmp_path / "d.png")[..., 0], np.rint(deep / 257).astype(np.uint8))
    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[0, 0] = [255, 0, 0, 255]
    rgba[1, 1] = [0, 0, 255, 128]
    Image.fromarray(rgba).save(tmp_path / "a.png")
    out = read_image(tmp_path / "a.png", background=(1.0, 1.0, 1.0))
    assert out[0, 0].tolist() == [255, 0, 0] and out[0, 1].tolist() == [255, 255, 255]
    assert out[1, 1].tolist() == [127, 127, 255]
    # An RGB or grey PNG with one transparent colour (a tRNS chunk, no alpha channel): that colour is the
    # background too (it kept its key colour).
    keyed = np.array([[[10, 20, 30], [200, 100, 50]]], np.uint8)
    Image.fromarray(keyed).save(tmp_path / "k.png", transparency=(10, 20, 30))
    assert read_image(tmp_path / "k.png", background=(1.0, 1.0, 1.0)).tolist() == [[[255, 255, 255], [200, 100, 50]]]
    Image.fromarray(np.array([[0, 90]], np.uint8)).save(tmp_path / "kg.png", transparency=0)
    assert read_image(tmp_path / "kg.png", background=(1.0, 0.0, 0.0)).tolist() == [[[255, 0, 0], [90, 90, 90]]]
