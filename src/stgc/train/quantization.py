"""Rate-aware fine-tuning (issue #17): render the model as the .stgc codec will store it.

During the run's last `train.quantization_aware.iterations` iterations every Gaussian attribute is replaced, in the
forward pass, by what `decode(encode(model))` gives at the configured quality (`stgc.codec.simulate_quantization`:
the codec's own domains, quantizer fitting, outlier guard and time-span scaling, without the entropy coding), and
the gradient passes straight through to the float parameters (x + (q(x) - x).detach()). The model so learns values
that survive the quantization: a Gaussian whose position or colour sits between two levels is moved to where the
rounded value renders well. Rotation and omega are seen canonicalized (unit quaternion), which renders the same.
The decoder MLP is not simulated: the codec stores it in float16 (relative error 2^-11).
"""

from __future__ import annotations

import numpy as np
import torch

from stgc.codec.format import simulate_quantization
from stgc.model import STGModel, ply_columns

from .config import QuantizationAwareConfig


class QuantizationSimulation:
    """The codec's quantization of a model's parameters, differentiable by the straight-through estimator."""

    def __init__(self, cfg: QuantizationAwareConfig):
        self.cfg = cfg

    def quantized_params(self, model: STGModel) -> dict[str, torch.Tensor]:
        """{param key: tensor} whose values are the codec's reconstruction and whose gradient is the identity."""
        quantized = simulate_quantization(model.to_ply_arrays(), model.variant, self.cfg.quality,
                                          position_bits=self.cfg.position_bits or None)
        out = {}
        for key, names in ply_columns(model.variant).items():
            param = model.params[key]
            values = torch.from_numpy(np.stack([quantized[name] for name in names], axis=1)).to(param)
            out[key] = param + (values - param).detach()
        return out
