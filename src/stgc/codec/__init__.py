"""stgc.codec: the .stgc compressed bitstream for trained Spacetime Gaussians (spec: docs/stgc-format.md).

encode/decode work on the official PLY field arrays (stgc.model.layout.ply_fields order) and need no model code;
compress_run/decompress go through stgc.model for the run directory layout.
"""

from .files import (
    CodecConfig,
    CompressResult,
    compress_run,
    decompress,
    encode_with_config,
    load_model,
    read_stgc,
    read_stgc_header,
    stgc_bytes_per_gaussian,
    stgc_file_bytes,
    write_stgc,
)
from .format import (
    DEFAULT_QUALITY,
    QUALITY_LEVELS,
    DecodedModel,
    StgcHeader,
    canonical_rotation,
    decode,
    encode,
    read_header,
)

__all__ = [
    "DEFAULT_QUALITY",
    "QUALITY_LEVELS",
    "CodecConfig",
    "CompressResult",
    "DecodedModel",
    "StgcHeader",
    "canonical_rotation",
    "compress_run",
    "decode",
    "decompress",
    "encode",
    "encode_with_config",
    "load_model",
    "read_header",
    "read_stgc",
    "read_stgc_header",
    "stgc_bytes_per_gaussian",
    "stgc_file_bytes",
    "write_stgc",
]
