"""The Spacetime Gaussians model: parameters, evaluation at time t, decoder, rendering, official PLY checkpoints."""

from stgc.model.config import DECODER_ACTIVATIONS, ModelConfig
from stgc.model.decoder import SandwichDecoder, camera_rays
from stgc.model.layout import VARIANTS, bytes_per_gaussian, ply_fields
from stgc.model.stg import (
    MIN_VISIBLE_OPACITY,
    NEAR_PLANE,
    PARAM_KEYS,
    ModelRender,
    RowsAt,
    STGModel,
    initial_log_scales,
    param_widths,
    ply_columns,
    rows_at,
)

__all__ = [
    "DECODER_ACTIVATIONS",
    "MIN_VISIBLE_OPACITY",
    "NEAR_PLANE",
    "PARAM_KEYS",
    "VARIANTS",
    "ModelConfig",
    "ModelRender",
    "RowsAt",
    "STGModel",
    "SandwichDecoder",
    "bytes_per_gaussian",
    "camera_rays",
    "initial_log_scales",
    "param_widths",
    "ply_columns",
    "ply_fields",
    "rows_at",
]
