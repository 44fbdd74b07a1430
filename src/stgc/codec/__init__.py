"""stgc.codec: the .stgc compressed bitstream for trained Spacetime Gaussians (spec: docs/stgc-format.md).

encode/decode work on the official PLY field arrays (stgc.model.layout.ply_fields order) and need no model code;
compress_run/decompress go through stgc.model for the run directory layout. A whole video (segments) is one
container of its segments' bitstreams (stgc.codec.video).
"""

from .files import (
    CodecConfig,
    CompressResult,
    VideoCompressResult,
    compress_run,
    decompress,
    encode_with_config,
    load_model,
    load_video_segment,
    model_digest,
    read_stgc,
    read_stgc_header,
    read_stgc_metadata,
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
    simulate_quantization,
)
from .video import (
    VideoIndex,
    VideoSegmentEntry,
    decode_video,
    encode_video,
    is_video_stgc,
    read_video_index,
    read_video_segment,
)

__all__ = [
    "DEFAULT_QUALITY",
    "QUALITY_LEVELS",
    "CodecConfig",
    "CompressResult",
    "DecodedModel",
    "StgcHeader",
    "VideoCompressResult",
    "VideoIndex",
    "VideoSegmentEntry",
    "canonical_rotation",
    "compress_run",
    "decode",
    "decode_video",
    "decompress",
    "encode",
    "encode_video",
    "encode_with_config",
    "is_video_stgc",
    "load_model",
    "load_video_segment",
    "model_digest",
    "read_header",
    "read_stgc",
    "read_stgc_header",
    "read_stgc_metadata",
    "read_video_index",
    "read_video_segment",
    "simulate_quantization",
    "stgc_bytes_per_gaussian",
    "stgc_file_bytes",
    "write_stgc",
]
