"""Renders of a synthetic model before and after the codec (through stgc.model and stgc.render)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from stgc.codec import DEFAULT_QUALITY, decode, encode
from stgc.codec.synthetic import synthetic_model
from stgc.data.cameras import Camera
from stgc.model import STGModel

from .helpers import psnr


def _cameras() -> list[Camera]:
    # Close enough that a pixel (~1.5 cm at 6 m with f = 400) is finer than most Gaussians (3 cm): errors show.
    K = np.array([[400.0, 0.0, 80.0], [0.0, 400.0, 60.0], [0.0, 0.0, 1.0]])
    w2c = np.eye(4)
    w2c[2, 3] = 6.0
    return [Camera("front", 0, t, K, w2c, 160, 120) for t in (0.15, 0.8)]


def _render(arrays, variant, decoder) -> list[np.ndarray]:
    model = STGModel.from_ply_arrays(arrays, variant, decoder)
    with torch.no_grad():
        return [model.render(cam, backend="torch").rgb.clamp(0, 1).numpy() for cam in _cameras()]


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_default_quality_renders_are_nearly_identical(variant):
    arrays, decoder = synthetic_model(3000, variant, seed=11)
    before = _render(arrays, variant, decoder)
    assert min(float(img.std()) for img in before) > 0.05  # the views see actual structure
    decoded = decode(encode(arrays, variant, decoder, DEFAULT_QUALITY))
    after = _render(decoded.arrays, variant, decoded.decoder_state)
    scores = [psnr(a, b) for a, b in zip(before, after)]
    assert min(scores) > 45.0, scores
    # And the codec is not a no-op the renderer cannot see: the coarsest level costs visible quality.
    coarse = decode(encode(arrays, variant, decoder, 1))
    assert np.mean([psnr(a, b) for a, b in zip(before, _render(coarse.arrays, variant, coarse.decoder_state))]) < np.mean(scores)
