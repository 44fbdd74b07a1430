"""Rate-aware fine-tuning (issue #17): render the model as the .stgc codec will store it.

During the run's last `train.quantization_aware.iterations` iterations every Gaussian attribute is replaced, in the
forward pass, by what `decode(encode(model))` gives (`stgc.codec.simulate_quantization`: the codec's own domains,
quantizer fitting, outlier guard and time-span scaling, without the entropy coding), and the gradient passes
straight through to the float parameters (x + (q(x) - x).detach()). The model so learns values that survive the
quantization. Rotation and omega are quantized as the codec stores them (canonical: unit quaternion, largest component
positive) and seen scaled back to the parameter's own sign and norm, which renders the same and keeps the straight-
through gradient pointing the parameter's way (`_parameter_frame`). As `compress_run`
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

With `mask` the window also learns which Gaussians are worth their bits (`GaussianMask`, after Compact3D's learned
mask): a logit per Gaussian whose sigmoid multiplies the temporal opacity. The rate term then prices the file rather
than the average Gaussian: the sum over Gaussians of mask x estimated bits (the GROUPS' code lengths plus an equal
share of the position and omega sections, which the rate term does not differentiate) over the Gaussian count (of
those some frame shows) when the window opened. With every mask at 1 this is the plain rate term plus a constant, so
lambda means the same with and without the mask; what the mask adds is that fading a Gaussian out saves lambda x its
bits, which the rendering loss must outweigh for it to stay. The mask is soft while it learns (a Gaussian that fades
makes its neighbours' gradients take over its work, so redundant Gaussians do not all go at once, as they do with a
binary forward pass) and is settled for the window's last MASK_SETTLE_FRACTION: Gaussians below one half are
removed, the others keep their mask baked into their opacity, and the rest of the window trains the model without
the removed ones.
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
from stgc.codec.rate import code_lengths, estimate_section_bits
from stgc.codec.views import Corrections, optimise_on_views
from stgc.data.dataset import Dataset
from stgc.errors import StgcError
from stgc.model import MIN_VISIBLE_OPACITY, STGModel, ply_columns

from .config import QuantizationAwareConfig
from .densify import describe_nonfinite, prune_mask_nonfinite


class QuantizationSimulation:
    """The codec's quantization of a model's parameters, differentiable by the straight-through estimator."""

    def __init__(self, cfg: QuantizationAwareConfig):
        self.cfg = cfg
        # (group_bits, step_scales) of the allocation chosen when the window opened (or, with remeasure_at_settle,
        # when the mask settled); None before, or for the ladder.
        self.settings: tuple[dict[str, int], dict[str, list[float]]] | None = None
        self.allocation: dict[str, Any] | None = None  # its summary, for the run's records
        self.mask: GaussianMask | None = None  # with cfg.mask: created on the window's first step
        self.mask_settled = False  # the mask's Gaussians were removed or baked; no mask from then on

    def prepare(self, model: STGModel, dataset: Dataset, corrections: Corrections | None) -> None:
        """Choose the bit depths on the model as it is now: when the window opens, and again once after the mask
        settles with remeasure_at_settle (no-op while chosen, or for the ladder)."""
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
        the rate term's estimated bits per Gaussian, differentiable, or None when rate_weight is 0). With the mask,
        the rate is that of the kept Gaussians per Gaussian of the window's start, differentiable in the mask."""
        nonfinite = prune_mask_nonfinite(model)
        if bool(nonfinite.any()):
            # Density control leaves such rows to this while the learned mask keeps a logit per row (the codec
            # would refuse them with a less useful message).
            raise StgcError(
                f"training diverged in the rate-aware window: the last optimizer step made "
                f"{describe_nonfinite(model, nonfinite)} non-finite although the loss was finite, and "
                + ("the learned mask keeps one logit per Gaussian, so none can be removed; lower the learning rates "
                   "of those parameters (train.lr) or train.quantization_aware.mask_lr / rate_weight"
                   if self.mask is not None else
                   "the codec cannot store them; lower the learning rates of those parameters (train.lr)")
                + " and train (or fine-tune) again")
        if self.cfg.mask and self.mask is None and not self.mask_settled:
            self.mask = GaussianMask(model.num_gaussians, self.cfg.mask_lr, reference_count=int(_visible(model).sum()))
        if self.mask is not None and len(self.mask) != model.num_gaussians:
            raise RuntimeError(
                f"train.quantization_aware.mask: the model has {model.num_gaussians} Gaussians but the mask "
                f"{len(self.mask)}: something else (density control, error-guided sampling or compaction) changed "
                "the rows inside the rate-aware window; end them before the window opens")
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
            if self.mask is None:
                rate = RateTerm.bits_per_gaussian(model, keep, groups)
            else:
                rate = RateTerm.masked_bits(model, keep, groups, self.mask)
        frame = _parameter_frame(arrays, keep)
        out = {}
        for key, names in ply_columns(model.variant).items():
            param = model.params[key]
            values = np.stack([arrays[name] for name in names], axis=1)
            values[keep] = np.stack([stored[name] for name in names], axis=1)
            if key in ("rotation", "omega"):
                values[keep] *= frame[:, None]
            out[key] = param + (torch.from_numpy(values).to(param) - param).detach()
        return out, rate

    def settle_mask(self, model: STGModel) -> torch.Tensor | None:
        """End the mask's learning: bake each kept Gaussian's mask into its opacity (sigmoid(o) x mask) and return
        the rows to keep (mask >= 1/2) for the caller to prune with; None when there is no mask to settle. With
        remeasure_at_settle the depths are dropped, to be measured again on the pruned model."""
        if self.mask is None:
            return None
        with torch.no_grad():
            factor = torch.sigmoid(self.mask.logits.detach())
            if not bool((factor >= 0.5).any()):  # an empty model would train on, render nothing and crash later
                raise StgcError(f"the learned mask faded out all {len(factor)} Gaussians: "
                                f"train.quantization_aware.rate_weight {self.cfg.rate_weight} is too large for this "
                                f"model (or mask_lr {self.cfg.mask_lr} too fast); lower it")
            opacity = (torch.sigmoid(model.params["opacity"].detach()[:, 0]) * factor).clamp(1e-6, 1 - 1e-6)
            model.replace_param("opacity", torch.logit(opacity)[:, None], reset_moments=False)
        keep = factor >= 0.5
        self.mask, self.mask_settled = None, True
        if self.cfg.remeasure_at_settle and self.cfg.allocation == "optimised":
            self.settings = None  # measured again (prepare) on the first rendering of the model the mask leaves
        return keep

    def state_dict(self) -> dict[str, Any]:
        return {"settings": self.settings, "allocation": self.allocation,
                "mask": None if self.mask is None else self.mask.state_dict(), "mask_settled": self.mask_settled}

    def load_state_dict(self, state: Mapping[str, Any] | None) -> None:
        if state and state.get("settings") is not None:
            group_bits, step_scales = state["settings"]
            self.settings = ({str(k): int(v) for k, v in group_bits.items()},
                             {str(k): [float(x) for x in v] for k, v in step_scales.items()})
            self.allocation = state.get("allocation")
        if state and state.get("mask") is not None:
            self.mask = GaussianMask.from_state_dict(state["mask"], self.cfg.mask_lr)
        self.mask_settled = bool(state and state.get("mask_settled"))


def _parameter_frame(arrays: Mapping[str, np.ndarray], keep: np.ndarray) -> np.ndarray:
    """Per kept Gaussian, the factor s |q| that takes the codec's canonical (q, omega) (`canonical_rotation`:
    divided by s |q|, s the sign of q's largest-magnitude component) back to the parameter's own scale and sign.

    Both render the same rotation, but the straight-through estimator hands the gradient of what the forward pass
    used to the parameter unchanged: with the canonical pair it would point against the parameter's true gradient
    wherever s = -1 (every step uphill there) and be |q| times too large. A zero quaternion, which the codec stores
    as the direction of its omega, keeps the codec's pair (factor 1)."""
    rotation = np.stack([arrays[f"rot_{i}"] for i in range(4)], axis=1)[keep].astype(np.float64)
    norm = np.linalg.norm(rotation, axis=1)
    largest = np.take_along_axis(rotation, np.argmax(np.abs(rotation), axis=1)[:, None], axis=1)[:, 0]
    return np.where(norm > 0, np.where(largest < 0, -norm, norm), 1.0)


class RateTerm:
    """The estimated bits per Gaussian of the attribute groups whose cost follows their values' histogram.

    Left out: positions (stored as deltas along the Morton curve, so what they cost is how densely the Gaussians
    lie, not which values they take) and omega (scaled by the canonical quaternion's sign and norm; 2-3 % of a
    file). Rotation is the smallest-three of the canonical quaternion, as stored, and the index of its largest
    component (a constant per Gaussian: it prices the Gaussian for the mask, and has no gradient)."""

    GROUPS = ("TCEN", "TSCL", "MOTN", "FDC_", "OPAC", "SCAL", "ROTN", "FT__")

    UNPRICED = ("POSI", "OMGA")  # their sections' bits are shared equally among the Gaussians (mask only)

    @staticmethod
    def bits_per_gaussian(model: STGModel, keep: np.ndarray, groups: list[QuantizedGroup]) -> torch.Tensor:
        """Sum over the visible Gaussians (`keep`) and the GROUPS' stored components of each value's code length,
        interpolated between its two nearest codes, divided by the number of visible Gaussians."""
        return RateTerm.row_bits(model, keep, groups).sum() / max(int(keep.sum()), 1)

    @staticmethod
    def masked_bits(model: STGModel, keep: np.ndarray, groups: list[QuantizedGroup],
                    mask: GaussianMask) -> torch.Tensor:
        """Sum over the visible Gaussians of (mask's keep factor) x (their code lengths plus an equal share of the
        UNPRICED sections' estimated bits, estimated once, on the mask's first step: it changes slowly and costs
        a tenth of an iteration), divided by the mask's reference count (the window's start)."""
        if mask.shared_bits is None:
            unpriced = estimate_section_bits([g for g in groups if g.tag in RateTerm.UNPRICED])
            mask.shared_bits = sum(unpriced.values()) / max(int(keep.sum()), 1)
        rows = torch.from_numpy(np.flatnonzero(keep))
        per_row = RateTerm.row_bits(model, keep, groups) + mask.shared_bits
        return (mask.keep_factor()[rows].double() * per_row).sum() / mask.reference_count

    @staticmethod
    def row_bits(model: STGModel, keep: np.ndarray, groups: list[QuantizedGroup]) -> torch.Tensor:
        """[visible rows] each visible Gaussian's code lengths over the GROUPS' stored components, each interpolated
        between its value's two nearest codes (the quaternion's largest index: its own code's length)."""
        rows = torch.from_numpy(np.flatnonzero(keep))
        total = torch.zeros(len(rows), dtype=torch.float64)
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
                total = total + lengths[below] * (1 - frac) + lengths[below + 1] * frac
            if group.group.domain == QUAT_SMALLEST3:  # the index row, stored in ROTN beside the three
                largest = group.codes[3].astype(np.int64)
                total = total + torch.from_numpy(code_lengths(largest, 4)[largest])
        return total


# Every Gaussian starts nearly fully kept (sigmoid(3) = 0.95): the mask costs the model little at the start, and
# it takes a run of steps that agree, not one noisy step, to fade a Gaussian out.
MASK_INIT_LOGIT = 3.0
MASK_SETTLE_FRACTION = 0.2  # the window's last fifth trains without the mask, on the Gaussians it kept


class GaussianMask:
    """A learned keep factor per Gaussian, sigmoid(logit), that multiplies its opacity, with its own Adam."""

    def __init__(self, count: int, lr: float, logits: torch.Tensor | None = None, reference_count: int | None = None):
        start = torch.full((count,), MASK_INIT_LOGIT) if logits is None else logits.detach().float().clone()
        self.logits = torch.nn.Parameter(start)
        self.optimizer = torch.optim.Adam([self.logits], lr=lr, eps=1e-15)
        self.reference_count = int(reference_count or count)  # the rate's denominator: the visible count at the start
        self.shared_bits: float | None = None  # RateTerm.masked_bits' share of the unpriced sections per Gaussian

    def __len__(self) -> int:
        return int(self.logits.shape[0])

    def keep_factor(self) -> torch.Tensor:
        """[N] each Gaussian's keep factor in (0, 1), differentiable."""
        return torch.sigmoid(self.logits)

    def step(self) -> None:
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def state_dict(self) -> dict[str, Any]:
        return {"logits": self.logits.detach().clone(), "optimizer": self.optimizer.state_dict(),
                "reference_count": self.reference_count, "shared_bits": self.shared_bits}

    @classmethod
    def from_state_dict(cls, state: Mapping[str, Any], lr: float) -> GaussianMask:
        mask = cls(len(state["logits"]), lr, logits=state["logits"], reference_count=state["reference_count"])
        mask.optimizer.load_state_dict(state["optimizer"])
        mask.shared_bits = state.get("shared_bits")
        for group in mask.optimizer.param_groups:
            group["lr"] = lr
        return mask


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
        norm = quaternion.norm(dim=0)
        # A zero quaternion (official error-guided points) has no direction to move: no rate gradient, where 1/|q|
        # gave it about 1e12 (Adam's second moment then froze that row's rotation).
        unit = quaternion * torch.where(norm > ZERO_QUATERNION, sign / norm.clamp_min(ZERO_QUATERNION),
                                        torch.zeros_like(norm))
        others = torch.ones_like(quaternion, dtype=torch.bool)
        others[largest, torch.arange(quaternion.shape[1])] = False
        rest = unit.T[others.T].reshape(-1, 3).T
        return list(rest)
    assert domain == LINEAR, domain
    return fields


ZERO_QUATERNION = 1e-6  # a norm below it: a rotation too short to have a direction worth pricing


def _visible(model: STGModel) -> np.ndarray:
    """Rows some frame shows: what `compress_run` keeps (drop_invisible, with its margin)."""
    with torch.no_grad():
        return (model.peak_temporal_opacity() >= MIN_VISIBLE_OPACITY * (1.0 - 1e-3)).cpu().numpy()
