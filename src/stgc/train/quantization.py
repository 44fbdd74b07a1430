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

With `rate_weight` (lambda) > 0 the loss also carries lambda x the estimated bits per Gaussian of the quantized
attributes (`RateTerm`): each stored component's code costs -log2 of its frequency among the model's own codes
(stgc.codec.rate), interpolated linearly between neighbouring codes so that the gradient moves a value toward the
cheaper of its two nearest codes. Training then trades distortion for rate: values gather on fewer, more frequent
codes, which the entropy coder stores in fewer bits at the same depth.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from stgc.codec.format import (
    LINEAR,
    QUAT_SMALLEST3,
    SIGMOID,
    TIME_SPAN,
    QuantizationMemo,
    QuantizedGroup,
    quantized_groups,
    simulate_quantization,
)
from stgc.codec.rate import code_lengths
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

    def quantized_params(self, model: STGModel) -> tuple[dict[str, torch.Tensor], torch.Tensor | None]:
        """({param key: tensor} whose values are the codec's reconstruction and whose gradient is the identity,
        the rate term's estimated bits per Gaussian, differentiable, or None when rate_weight is 0)."""
        keep = _visible(model)
        arrays = model.to_ply_arrays()
        group_bits, step_scales = self.settings or (None, None)
        visible = {k: v[keep] for k, v in arrays.items()}
        memo = QuantizationMemo(visible)  # the rate term reuses the simulation's quantization
        position_bits = self.cfg.position_bits or None
        stored = simulate_quantization(visible, model.variant, self.cfg.quality, position_bits=position_bits,
                                       group_bits=group_bits, step_scales=step_scales, memo=memo)
        rate = None
        if self.cfg.rate_weight > 0:
            groups = quantized_groups(visible, model.variant, self.cfg.quality, position_bits=position_bits,
                                      group_bits=group_bits, step_scales=step_scales, memo=memo)
            rate = RateTerm.bits_per_gaussian(model, keep, groups)
        out = {}
        for key, names in ply_columns(model.variant).items():
            param = model.params[key]
            values = np.stack([arrays[name] for name in names], axis=1)
            values[keep] = np.stack([stored[name] for name in names], axis=1)
            out[key] = param + (torch.from_numpy(values).to(param) - param).detach()
        return out, rate

    def state_dict(self) -> dict[str, Any]:
        return {"settings": self.settings, "allocation": self.allocation}

    def load_state_dict(self, state: Mapping[str, Any] | None) -> None:
        if state and state.get("settings") is not None:
            group_bits, step_scales = state["settings"]
            self.settings = ({str(k): int(v) for k, v in group_bits.items()},
                             {str(k): [float(x) for x in v] for k, v in step_scales.items()})
            self.allocation = state.get("allocation")


class RateTerm:
    """The estimated bits per Gaussian of the attribute groups whose cost follows their values' histogram.

    Left out: positions (stored as deltas along the Morton curve, so what they cost is how densely the Gaussians
    lie, not which values they take) and omega (scaled by the canonical quaternion's sign and norm; 2-3 % of a
    file). Rotation is the smallest-three of the canonical quaternion, as stored."""

    GROUPS = ("TCEN", "TSCL", "MOTN", "FDC_", "OPAC", "SCAL", "ROTN", "FT__")

    @staticmethod
    def bits_per_gaussian(model: STGModel, keep: np.ndarray, groups: list[QuantizedGroup]) -> torch.Tensor:
        """Sum over the visible Gaussians (`keep`) and the GROUPS' stored components of each value's code length,
        interpolated between its two nearest codes, divided by the number of visible Gaussians."""
        rows = torch.from_numpy(np.flatnonzero(keep))
        total = torch.zeros((), dtype=torch.float64)
        for group in groups:
            if group.tag not in RateTerm.GROUPS:
                continue
            values = _stored_components(model, group, rows)
            for row, (component, quantizer) in enumerate(zip(values, group.quantizers)):
                levels = quantizer.levels
                lengths = torch.from_numpy(code_lengths(group.codes[row], levels))
                code = (component.double() / quantizer.step - quantizer.zero_point).clamp(0, levels - 1)
                below = code.detach().floor().clamp(max=levels - 2).long()
                frac = code - below
                total = total + (lengths[below] * (1 - frac) + lengths[below + 1] * frac).sum()
        return total / max(len(rows), 1)


def _stored_components(model: STGModel, group: QuantizedGroup, rows: torch.Tensor) -> list[torch.Tensor]:
    """The differentiable values the codec quantizes for `group`, one [len(rows)] tensor per stored component,
    in the domain its quantizers were fitted in (the TIME_SPAN span and the quaternion's largest index are taken
    from the codec's own quantization: they are not what the rate term moves)."""
    where = {name: (key, i) for key, names in ply_columns(model.variant).items() for i, name in enumerate(names)}
    fields = [model.params[where[name][0]][rows, where[name][1]] for name in group.group.fields(model.variant)]
    domain = group.group.domain
    if domain == SIGMOID:
        return [torch.sigmoid(f) for f in fields]
    if domain == TIME_SPAN:
        span = torch.from_numpy(group.span)
        return [f * span.to(f) ** power for f, power in zip(fields, group.group.span_powers)]
    if domain == QUAT_SMALLEST3:
        quaternion = torch.stack(fields, dim=0)
        largest = torch.from_numpy(group.codes[3].astype(np.int64))
        sign = torch.where(quaternion.detach().gather(0, largest[None])[0] < 0, -1.0, 1.0).to(quaternion)
        unit = quaternion * (sign / quaternion.norm(dim=0).clamp_min(1e-12))
        others = torch.ones_like(quaternion, dtype=torch.bool)
        others[largest, torch.arange(quaternion.shape[1])] = False
        rest = unit.T[others.T].reshape(-1, 3).T
        return list(rest)
    assert domain == LINEAR, domain
    return fields


def _visible(model: STGModel) -> np.ndarray:
    """Rows some frame shows: what `compress_run` keeps (drop_invisible, with its margin)."""
    with torch.no_grad():
        return (model.peak_temporal_opacity() >= MIN_VISIBLE_OPACITY * (1.0 - 1e-3)).cpu().numpy()
