"""Configuration of the Spacetime Gaussians model (read by the CLI generator and the trainer)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, Literal, get_args

from stgc.model.layout import VARIANTS, Variant
from stgc.official import family_options, official_value

DecoderActivation = Literal["sigmoid", "clamp", "none"]
DECODER_ACTIVATIONS = get_args(DecoderActivation)
DecoderRayInput = Literal["auto", "on", "off"]
DECODER_RAY_INPUTS = get_args(DecoderRayInput)


@dataclass
class ModelConfig:
    variant: Variant = field(
        default="full",
        metadata={
            "help": "STG variant: 'full' (35 floats/Gaussian, 9-channel features + MLP decoder, the paper's model) "
            "or 'lite' (29 floats/Gaussian, RGB splatted directly)."
        },
    )
    decoder_activation: DecoderActivation | None = field(
        default=None,
        metadata={
            "help": "Output activation of the full model's decoder: 'sigmoid' (official 'sandwich', N3DV), "
            "'clamp' (official 'sandwichnoact', Technicolor) or 'none'; default: the official config of the data's "
            "family (stgc.official: clamp for Technicolor, else sigmoid)."
        },
    )
    trbf_scale_init: float | None = field(
        default=None,
        metadata={
            "help": "Initial stored (log) temporal scale s_t of every Gaussian; the temporal RBF width is exp(s_t). "
            "Equals minus the official --trbfslinit; default: the official config of the data's family "
            "(stgc.official: -2 for Technicolor, else 0)."
        },
    )
    opacity_init: float = field(
        default=0.1,
        metadata={"help": "Initial opacity sigmoid(o) of every Gaussian (official 0.1)."},
    )
    init_neighbours: int = field(
        default=3,
        metadata={"help": "Neighbours for the initial scale: log(sqrt(mean squared distance to the k nearest))."},
    )
    decoder_seed: int = field(
        default=0,
        metadata={"help": "Seed of the decoder's random initial weights (full variant)."},
    )
    decoder_ray_origin: DecoderRayInput = field(
        default="auto",
        metadata={"help": "let the decoder see the ray origin, i.e. the camera centre (official STG: on). Off, its "
                          "weights on the origin are zero and stay zero: colour may still depend on the viewing "
                          "direction, not on which camera looks, and the files stay official. auto: off for real "
                          "captures, whose cameras differ in exposure (the origin becomes a per-camera colour code "
                          "that held-out cameras do not share; the colour correction takes that role), on for "
                          "synthetic renders (docs/model.md)"},
    )
    decoder_ray_direction: DecoderRayInput = field(
        default="auto",
        metadata={"help": "let the decoder see the viewing direction (official STG: on). Off, its weights on the "
                          "direction are zero and stay zero: the colour of a point at a time is the same from every "
                          "camera, and the files stay official. auto: off where the source's reference method has "
                          "no view-dependent colour (Panoptic: there the direction becomes a per-camera colour "
                          "guess for held-out cameras), on for every other format (docs/model.md)"},
    )

    # How a run saved before these options existed was trained (stgc.config.from_saved).
    SAVED_BEFORE: ClassVar[dict[str, Any]] = {"decoder_ray_origin": "on", "decoder_ray_direction": "on"}

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"model.variant must be one of {VARIANTS}, got {self.variant!r}")
        if self.decoder_activation is not None and self.decoder_activation not in DECODER_ACTIVATIONS:
            raise ValueError(
                f"model.decoder_activation must be one of {DECODER_ACTIVATIONS}, got {self.decoder_activation!r}"
            )
        for name in ("decoder_ray_origin", "decoder_ray_direction"):
            # The trainer takes every value but 'on' and 'auto' as off: a typo would drop the input silently.
            if getattr(self, name) not in DECODER_RAY_INPUTS:
                raise ValueError(f"model.{name} must be one of {DECODER_RAY_INPUTS}, got {getattr(self, name)!r}")
        if not 0.0 < self.opacity_init < 1.0:
            raise ValueError(f"model.opacity_init must be in (0, 1), got {self.opacity_init}")
        if self.init_neighbours < 1:
            raise ValueError(f"model.init_neighbours must be >= 1, got {self.init_neighbours}")
        if self.trbf_scale_init is not None and not math.isfinite(self.trbf_scale_init):
            raise ValueError(f"model.trbf_scale_init must be finite, got {self.trbf_scale_init}")

    def resolved(self, family: str | None) -> ModelConfig:
        """This config with every option left unset (None) taken from the official config of the data's `family`
        (`Dataset.official_config`; stgc.official)."""
        return replace(self, **{name: official_value(f"model.{name}", family) for name in RESOLVED_BY_DATA
                                if getattr(self, name) is None})

    @property
    def is_resolved(self) -> bool:
        return all(getattr(self, name) is not None for name in RESOLVED_BY_DATA)


# Options a run leaves to the data's official config family (ModelConfig.resolved).
RESOLVED_BY_DATA = family_options("model.")


# The full model's decoder options: a lite model has no decoder.
DECODER_OPTIONS = ("decoder_activation", "decoder_seed", "decoder_ray_origin", "decoder_ray_direction")


def idle_model_options(model: ModelConfig) -> set[str]:
    """The model options (dotted, with their section) that act on nothing in a run with `model`: the decoder's
    for the lite variant. Given for such a run they are refused (`stgc.options.refuse_unused_model_options`)."""
    return {f"model.{name}" for name in DECODER_OPTIONS} if model.variant == "lite" else set()
