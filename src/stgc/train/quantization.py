"""Rate-aware fine-tuning (issue #17): render the model as the .stgc codec will store it.

During the run's last `train.quantization_aware.iterations` iterations every Gaussian attribute is replaced, in the
forward pass, by what `decode(encode(model))` gives (`stgc.codec.simulate_quantization`: the codec's own domains,
quantizer fitting, outlier guard and time-span scaling, without the entropy coding), and the gradient passes
straight through to the float parameters (x + (q(x) - x).detach()). The model so learns values that survive the
quantization. Rotation and omega are seen canonicalized (unit quaternion), which renders the same. As `compress_run`
does by default, Gaussians that no frame shows are left out of the quantizer fits (and pass through unchanged: they
are never rendered). The decoder MLP is not simulated: the codec stores it in float16 (relative error 2^-11).

The bit depths are those `stgc compress` would choose: the rd-optimised allocation measured on the model's training
views when the window opens (`allocation = "optimised"`, the codec's default), or the fixed ladder. They are kept
for the whole window (and across a resume, in the checkpoint).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from stgc.codec.format import simulate_quantization
from stgc.codec.views import Corrections, optimise_on_views
from stgc.data.dataset import Dataset
from stgc.model import MIN_VISIBLE_OPACITY, STGModel, ply_columns

from .config import QuantizationAwareConfig


class QuantizationSimulation:
    """The codec's quantization of a model's parameters, differentiable by the straight-through estimator."""

    def __init__(self, cfg: QuantizationAwareConfig):
        self.cfg = cfg
        # (group_bits, step_scales) of the allocation chosen when the window opened; None before, or for the ladder.
        self.settings: tuple[dict[str, int], dict[str, list[float]]] | None = None
        self.allocation: dict[str, Any] | None = None  # its summary, for the run's records

    def prepare(self, model: STGModel, dataset: Dataset, corrections: Corrections | None) -> None:
        """Choose the bit depths once, on the model as the window finds it (no-op when chosen or for the ladder)."""
        if self.cfg.allocation != "optimised" or self.settings is not None:
            return
        keep = _visible(model)
        kept = STGModel.from_ply_arrays({k: v[keep] for k, v in model.to_ply_arrays().items()}, model.variant,
                                        model.decoder_state(), decoder_activation=model.decoder_activation or "sigmoid")
        allocation = optimise_on_views(kept, dataset, self.cfg.quality, position_bits=self.cfg.position_bits,
                                       corrections=corrections, show_progress=False)
        self.settings = allocation.encoder_settings()
        self.allocation = allocation.summary()

    def quantized_params(self, model: STGModel) -> dict[str, torch.Tensor]:
        """{param key: tensor} whose values are the codec's reconstruction and whose gradient is the identity."""
        keep = _visible(model)
        arrays = model.to_ply_arrays()
        group_bits, step_scales = self.settings or (None, None)
        stored = simulate_quantization({k: v[keep] for k, v in arrays.items()}, model.variant, self.cfg.quality,
                                       position_bits=self.cfg.position_bits or None, group_bits=group_bits,
                                       step_scales=step_scales)
        out = {}
        for key, names in ply_columns(model.variant).items():
            param = model.params[key]
            values = np.stack([arrays[name] for name in names], axis=1)
            values[keep] = np.stack([stored[name] for name in names], axis=1)
            out[key] = param + (torch.from_numpy(values).to(param) - param).detach()
        return out

    def state_dict(self) -> dict[str, Any]:
        return {"settings": self.settings, "allocation": self.allocation}

    def load_state_dict(self, state: Mapping[str, Any] | None) -> None:
        if state and state.get("settings") is not None:
            group_bits, step_scales = state["settings"]
            self.settings = ({str(k): int(v) for k, v in group_bits.items()},
                             {str(k): [float(x) for x in v] for k, v in step_scales.items()})
            self.allocation = state.get("allocation")


def _visible(model: STGModel) -> np.ndarray:
    """Rows some frame shows: what `compress_run` keeps (drop_invisible, with its margin)."""
    with torch.no_grad():
        return (model.peak_temporal_opacity() >= MIN_VISIBLE_OPACITY * (1.0 - 1e-3)).cpu().numpy()
