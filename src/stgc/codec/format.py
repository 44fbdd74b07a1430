"""The .stgc bitstream: encode an STG model (official PLY field arrays) to bytes and decode it back.

Byte-level specification: docs/stgc-format.md. Summary: a 32-byte header (magic, version, variant, quality,
Gaussian count, section table size, CRC32s), a section table (one entry per attribute group with its bit depth
and per-component quantizer), then the section payloads (zstd frames of byte-plane-ordered integer codes, the
fp16 decoder MLP, and optional JSON metadata). Gaussians are stored in Morton order of their quantized positions.

Decoding treats the input as hostile: every size is checked against the file and against the Gaussian count
before anything large is allocated, and every problem surfaces as `stgc.errors.FormatError`.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zstandard

from stgc.errors import DataError, FormatError
from stgc.model.layout import NORMAL_FIELDS, VARIANTS, ply_fields
from stgc.model.layout import bytes_per_gaussian as ply_bytes_per_gaussian

from .quantize import (
    MAX_BITS,
    MIN_BITS,
    Quantizer,
    centre_encode,
    container_dtype,
    delta_decode,
    delta_encode,
    dequantize,
    fit_prediction,
    fit_quantizer,
    from_byte_planes,
    morton_order,
    predict_decode,
    predict_encode,
    prediction_size,
    quantize,
    to_byte_planes,
    unzigzag,
    zigzag,
)

MAGIC = b"STGC\r\n\x1a\n"  # the CR-LF / ^Z / LF tail catches text-mode and line-ending mangling, as PNG's does
# 2: motion and omega are stored scaled by each Gaussian's time span (TIME_SPAN); 3: FLAG_CENTRED; 4: FLAG_PREDICT
VERSION = 4
# A whole-video container of such files (stgc.codec.video); its own magic, so this reader names it instead of misreading.
VIDEO_MAGIC = b"STGV\r\n\x1a\n"
READABLE_VERSIONS = (2, 3, 4)  # versions 3 and 4 only add section flags: an older file is a valid newer one
QUALITY_LEVELS = (1, 2, 3, 4, 5)
DEFAULT_QUALITY = 3
DEFAULT_ZSTD_LEVEL = 19  # encoding is offline; 19 is ~3.5 % smaller than 12 (6x slower) and decodes as fast
_PROBE_LEVEL = 3  # zstd level used only to rank candidate layouts
_GUARD_RATIO = 4.0  # full range / central 99.8 % range above which the outlier guard adds bits
# Decoder-side caps: a file may not make us allocate more than this, whatever it claims.
MAX_GAUSSIANS = 1 << 27
# No valid file is larger than its model uncompressed (MAX_GAUSSIANS float32 PLY rows of the full variant): a larger
# one is refused before it is read into memory.
MAX_FILE_BYTES = MAX_GAUSSIANS * ply_bytes_per_gaussian("full")

MAX_SECTIONS = 64
MAX_DECODER_BYTES = 64 << 20
MAX_META_BYTES = 1 << 20
# A zstd block holds at most 128 KiB of content and costs at least 4 bytes (3-byte header + 1 RLE byte), so a
# frame cannot expand by more than 32768x; a claimed raw size beyond that is a lie and is rejected unread.
ZSTD_MAX_EXPANSION = 1 << 15
ZSTD_SLACK = 1 << 17
# A frame may ask for a window of up to 2**max(23, min(27, bit_length(raw_size))) bytes (spec §6).
ZSTD_MIN_WINDOW_LOG = 23
ZSTD_MAX_WINDOW_LOG = 27


def read_capped(path: str | os.PathLike) -> bytes:
    """The bytes of a .stgc file, refused unread when it is larger than any valid one."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise DataError(path, f"cannot read .stgc file ({exc.strerror})") from None
    if size > MAX_FILE_BYTES:
        raise FormatError(path, f"{size} bytes is larger than any valid .stgc file")
    if not path.is_file():  # a device or a pipe says size 0 and may never end
        raise FormatError(path, "not a regular file")
    try:
        return path.read_bytes()
    except OSError as exc:  # permission, I/O error: as a missing file, never a bare OSError
        raise DataError(path, f"cannot read .stgc file ({exc.strerror})") from None


_HEADER = struct.Struct("<8sHBBIHHII")  # magic version variant quality N sections flags table_size table_crc
_HEADER_CRC = struct.Struct("<I")
HEADER_SIZE = _HEADER.size + _HEADER_CRC.size  # 32
_ENTRY = struct.Struct("<4sBBBBIII")  # tag codec bits components flags raw_size payload_size payload_crc
_QPARAM = struct.Struct("<dq")  # step (float64), zero_point (int64)
_COEFFICIENT = struct.Struct("<h")  # one prediction coefficient (FLAG_PREDICT), units of 2**-PREDICTION_SHIFT

_VARIANT_CODES = {"full": 1, "lite": 2}
_VARIANT_NAMES = {v: k for k, v in _VARIANT_CODES.items()}

CODEC_STORED = 0
CODEC_ZSTD = 1
FLAG_DELTA = 1  # codes are delta + zigzag coded along the stored (Morton) order
FLAG_INTERLEAVE = 2  # byte planes hold each Gaussian's components side by side (else one component after another)
# Codes are zigzag(code - centre) in a (bits+1)-bit container, the centre folded into the quantizer's zero point
# (value = (signed + zero_point) * step). Not with FLAG_DELTA, not for quaternion groups.
FLAG_CENTRED = 4
# With FLAG_CENTRED only: each component's signed codes are stored as the residual of a linear prediction from the
# components before it (coefficients in the section table), wrapped into the same range (quantize.predict_encode).
FLAG_PREDICT = 8
KNOWN_FLAGS = FLAG_DELTA | FLAG_INTERLEAVE | FLAG_CENTRED | FLAG_PREDICT
# The version that introduced each later flag: no encoder of an older version wrote it, and that version's decoder
# refused it, so an older file holding one is damaged or forged, not a valid file.
FLAG_SINCE_VERSION = {FLAG_CENTRED: ("CENTRED", 3), FLAG_PREDICT: ("PREDICT", 4)}

# Domains: how a component is mapped before uniform quantization (and back after).
LINEAR = "linear"
SIGMOID = "sigmoid"  # opacity: quantized as sigmoid(logit) in [0,1], the quantity the renderer blends with
# Unit quaternion as "smallest three": the three components other than the largest-magnitude one (which the
# canonical sign makes positive, so it is sqrt(1 - sum of the others' squares)), then that one's index 0..3.
# The three lie in [-1/sqrt(2), 1/sqrt(2)], so the same bits buy 1.4x finer steps than quantizing all four.
QUAT_SMALLEST3 = "quat-smallest3"
_OPACITY_CLAMP = 1e-7  # logit(1 - 1e-7) = 16.1: beyond that the opacity is 1 in float32 anyway
# Time-polynomial coefficient c of power p moves a Gaussian by c * dt**p, dt = t - trbf_center, but only while
# the Gaussian is visible: temporal opacity exp(-(dt / exp(trbf_scale))**2) is 0.018 at dt = 2 exp(trbf_scale),
# and t stays in [0, 1]. So c is stored as c * span**p with span = min(max(|mu|, |1 - mu|), 2 exp(s)) clipped to
# [SPAN_MIN, 1]: a uniform step then bounds the displacement error over the time the Gaussian is seen, instead
# of spending the levels on coefficients of short-lived Gaussians whose high powers never act (for mu outside
# [0, 1] the clip to 1 lets it grow by max(|mu|, |1 - mu|)**p; part of the format, spec §2.1). mu and s are the
# *decoded* trbf values, so encoder and decoder compute the same span.
TIME_SPAN = "time-span"
SPAN_SIGMAS = 2.0
SPAN_MIN = 0.01  # below ~1 % of the sequence a Gaussian lives for about one frame at 100 frames


@dataclass(frozen=True)
class AttributeGroup:
    tag: bytes
    fields_full: tuple[str, ...]
    fields_lite: tuple[str, ...]
    domain: str
    bits_by_quality: tuple[int, int, int, int, int]
    span_powers: tuple[int, ...] = ()  # TIME_SPAN domain: the power of dt each component multiplies
    # The components play the same role (world axes, a quaternion's components): one precision suits them all,
    # so an encoder has no reason to give them different step scales (see encode's step_scales).
    exchangeable: bool = False

    def fields(self, variant: str) -> tuple[str, ...]:
        return self.fields_full if variant == "full" else self.fields_lite


def _names(prefix: str, n: int) -> tuple[str, ...]:
    return tuple(f"{prefix}_{i}" for i in range(n))


# Bit depth per quality level 1..5 (default 3). Positions need the most: the error is a world-space offset that
# must stay far below a pixel (docs/stgc-format.md, "Position precision"). trbf_center gets more bits than the
# other scalars because temporal opacity exp(-((t - mu_t) / s_t)^2) turns a small mu_t shift into a large
# opacity change for short-lived Gaussians. The rest follows a per-group sensitivity sweep of test PSNR on the two
# trained shared models (docs/stgc-format.md section 7): motion, log-scale and rotation are the most visible
# after position; omega and f_t the least.
GROUPS: tuple[AttributeGroup, ...] = (
    AttributeGroup(b"POSI", ("x", "y", "z"), ("x", "y", "z"), LINEAR, (12, 13, 14, 16, 18), exchangeable=True),
    AttributeGroup(b"TCEN", ("trbf_center",), ("trbf_center",), LINEAR, (8, 9, 9, 11, 13)),
    AttributeGroup(b"TSCL", ("trbf_scale",), ("trbf_scale",), LINEAR, (5, 6, 7, 8, 9)),
    AttributeGroup(b"MOTN", _names("motion", 9), _names("motion", 9), TIME_SPAN, (5, 6, 7, 8, 9),
                   span_powers=(1, 1, 1, 2, 2, 2, 3, 3, 3)),
    AttributeGroup(b"FDC_", _names("f_dc", 6), _names("f_dc", 3), LINEAR, (5, 6, 7, 8, 10)),
    AttributeGroup(b"OPAC", ("opacity",), ("opacity",), SIGMOID, (5, 6, 7, 8, 9)),
    AttributeGroup(b"SCAL", _names("scale", 3), _names("scale", 3), LINEAR, (5, 6, 8, 9, 10), exchangeable=True),
    AttributeGroup(b"ROTN", _names("rot", 4), _names("rot", 4), QUAT_SMALLEST3, (5, 6, 7, 8, 9), exchangeable=True),
    AttributeGroup(b"OMGA", _names("omega", 4), _names("omega", 4), TIME_SPAN, (3, 4, 4, 6, 8),
                   span_powers=(1, 1, 1, 1)),
    AttributeGroup(b"FT__", _names("f_t", 3), (), LINEAR, (3, 3, 3, 5, 8)),
)
GROUP_BY_TAG = {g.tag: g for g in GROUPS}
GROUP_TAGS = frozenset(g.tag.decode("latin-1") for g in GROUPS)
TAG_DECODER = b"DECO"
TAG_META = b"META"
# The table's `bits` of these sections: fixed by the spec (every version wrote these), checked by the decoder.
DECODER_BITS = 16
META_BITS = 8
_DECO, _META = TAG_DECODER.decode("latin-1"), TAG_META.decode("latin-1")

_DTYPE_CODES: dict[np.dtype, int] = {np.dtype(np.float16): 1, np.dtype(np.float32): 2}
_DTYPE_BY_CODE: dict[int, np.dtype] = {v: k for k, v in _DTYPE_CODES.items()}
_FP16_MAX = 65504.0


def groups_for(variant: str) -> tuple[AttributeGroup, ...]:
    return tuple(g for g in GROUPS if g.fields(variant))


def bits_for(group: AttributeGroup, quality: int) -> int:
    if quality not in QUALITY_LEVELS:
        raise ValueError(f"quality must be one of {QUALITY_LEVELS}, got {quality!r}")
    return group.bits_by_quality[quality - 1]


@dataclass(frozen=True)
class SectionInfo:
    """One entry of the section table, as read from (or written to) a file."""

    tag: str
    codec: int
    bits: int
    components: int
    flags: int
    raw_size: int
    payload_size: int
    payload_crc: int
    quantizers: tuple[Quantizer, ...] = ()
    prediction: tuple[int, ...] = ()  # FLAG_PREDICT: the strictly lower-triangular coefficients, row by row

    @property
    def table_bytes(self) -> int:
        return _ENTRY.size + self.components * _QPARAM.size + len(self.prediction) * _COEFFICIENT.size

    def prediction_matrix(self) -> np.ndarray:
        matrix = np.zeros((self.components, self.components), np.int64)
        matrix[np.tril_indices(self.components, -1)] = self.prediction
        return matrix


@dataclass(frozen=True)
class StgcHeader:
    version: int
    variant: str
    quality: int
    num_gaussians: int
    file_size: int
    sections: tuple[SectionInfo, ...]

    @property
    def bytes_per_gaussian(self) -> float:
        return self.file_size / self.num_gaussians if self.num_gaussians else float("nan")

    def section_bytes(self) -> dict[str, int]:
        """Payload bytes per section tag (the table and header are not included)."""
        return {s.tag: s.payload_size for s in self.sections}


@dataclass
class DecodedModel:
    """A decoded .stgc file. `arrays` follows ply_fields(variant) (normals are zeros), Gaussians in Morton order."""

    arrays: dict[str, np.ndarray]
    variant: str
    decoder_state: dict[str, np.ndarray] | None
    header: StgcHeader
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def num_gaussians(self) -> int:
        return self.header.num_gaussians


# =====================================================================================================================
# Encoder
# =====================================================================================================================

def canonical_rotation(rot: np.ndarray, omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scale (q, omega) jointly by +-1/|q| so that |q| = 1 and q's largest-magnitude component is positive.

    STG rotates by normalize(q + omega * dt), which is invariant to any positive common factor of q and omega, and
    maps to the same rotation under a common sign flip; so this changes nothing rendered while bounding q to
    [-1, 1]. A zero quaternion (the official error-guided sampling creates them) cannot be stored as a unit one:
    with omega != 0 it rotates by normalize(omega * dt) = +-omega/|omega| at every dt != 0, which q = omega/|omega|,
    omega' = omega / (2 |omega|) renders too (q + omega' dt = q (1 + dt/2) keeps its direction for |dt| < 2). With
    omega = 0 as well it is left as is."""
    rot = np.asarray(rot, dtype=np.float64)
    omega = np.asarray(omega, dtype=np.float64)
    omega_norm = np.linalg.norm(omega, axis=1, keepdims=True)
    still = (np.linalg.norm(rot, axis=1, keepdims=True) == 0) & (omega_norm > 0)
    if still.any():
        direction = omega / np.where(omega_norm > 0, omega_norm, 1.0)
        rot = np.where(still, direction, rot)
        omega = np.where(still, direction / 2, omega)
    norm = np.linalg.norm(rot, axis=1, keepdims=True)
    largest = np.take_along_axis(rot, np.argmax(np.abs(rot), axis=1)[:, None], axis=1)
    sign = np.where(largest < 0, -1.0, 1.0)
    factor = np.where(norm > 0, sign / np.where(norm > 0, norm, 1.0), 1.0)
    return rot * factor, omega * factor


def time_span(trbf_center: np.ndarray, trbf_scale: np.ndarray) -> np.ndarray:
    """Per-Gaussian time span over which its motion acts (see TIME_SPAN), float64 in [SPAN_MIN, 1]."""
    mu = np.asarray(trbf_center, dtype=np.float64)
    with np.errstate(over="ignore"):  # a huge trbf_scale means "always visible": exp -> inf, then min() drops it
        visible = SPAN_SIGMAS * np.exp(np.asarray(trbf_scale, dtype=np.float64))
    return np.clip(np.minimum(np.maximum(np.abs(mu), np.abs(1.0 - mu)), visible), SPAN_MIN, 1.0)


def _span_factors(group: AttributeGroup, span: np.ndarray) -> np.ndarray:
    """[C, N] multipliers span**p of a TIME_SPAN group."""
    return span[None, :] ** np.asarray(group.span_powers, dtype=np.float64)[:, None]


def _to_domain(values: np.ndarray, domain: str) -> np.ndarray:
    """[C, N] field values -> [C', N] values to quantize (TIME_SPAN groups are scaled by the caller)."""
    if domain == SIGMOID:
        return 0.5 * (1.0 + np.tanh(0.5 * values))  # overflow-free sigmoid
    if domain == QUAT_SMALLEST3:
        largest = np.argmax(np.abs(values), axis=0)
        keep = np.ones_like(values, dtype=bool)
        keep[largest, np.arange(values.shape[1])] = False
        rest = values.T[keep.T].reshape(-1, 3).T  # the other three, in component order
        return np.concatenate([rest, largest[None].astype(np.float64)], axis=0)
    return values


def _from_domain(values: np.ndarray, domain: str) -> np.ndarray:
    """Inverse of _to_domain (values: dequantized [C', N]; for quaternions the last row holds integer indices)."""
    if domain == SIGMOID:
        p = np.clip(values, _OPACITY_CLAMP, 1.0 - _OPACITY_CLAMP)
        return np.log(p) - np.log1p(-p)
    if domain == QUAT_SMALLEST3:
        rest, largest = values[:3], values[3].astype(np.int64)
        n = values.shape[1]
        out = np.empty((4, n), dtype=np.float64)
        out[largest, np.arange(n)] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(rest * rest, axis=0)))
        keep = np.ones((4, n), dtype=bool)
        keep[largest, np.arange(n)] = False
        out.T[keep.T] = rest.T.reshape(-1)
        return out
    return values


def outlier_guard_extra_bits(values: np.ndarray) -> int:
    """The bits to add to a group's depth to keep the bulk's precision when a few outliers stretch the range.

    The quantizer step follows the full [min, max] range, so one Gaussian far out (a floater, a stray motion
    coefficient) would coarsen every other Gaussian's step. Applied to the linear and time-span groups (in their
    quantized domain). When the full span exceeds _GUARD_RATIO (4) times the
    span of the central 99.8 % (0.1 to 99.9 percentile) of any component, ceil(log2(ratio / 4)) bits are added, up
    to +8 bits (and MAX_BITS in all). Outlier-free heavy-tailed data (ratio ~2) stays below 4 and
    is unaffected. A component whose central 99.8 % is one value has no spread to keep: it adds nothing (its
    ratio would be infinite). It depends on the values only, not on the depth (the allocation's trials reuse it)."""
    if values.shape[1] < 2:
        return 0
    lo, hi = np.quantile(values, [0.001, 0.999], axis=1)
    full = values.max(axis=1) - values.min(axis=1)
    robust = hi - lo
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        ratios = np.where((full > 0) & (robust > 0), full / np.where(robust > 0, robust, 1.0), 1.0)
    ratio = float(min(np.max(ratios), _GUARD_RATIO * 2.0**8))  # (a tiny central spread overflows to inf)
    extra = int(np.ceil(np.log2(ratio / _GUARD_RATIO))) if ratio > _GUARD_RATIO else 0
    return min(extra, 8)


def _fit_group(values: np.ndarray, domain: str, bits: int,
               coarsen: Sequence[float] | None = None) -> tuple[Quantizer, ...]:
    stored = values[:3] if domain == QUAT_SMALLEST3 else values  # the quaternion's index row is kept as is
    factors = coarsen if coarsen is not None else [1.0] * len(stored)
    quantizers = tuple(fit_quantizer(v, bits, float(f)) for v, f in zip(stored, factors))
    if domain == QUAT_SMALLEST3:
        quantizers += (Quantizer(step=1.0, zero_point=0, bits=bits),)
    return quantizers


def _validated_columns(arrays: Mapping[str, np.ndarray], variant: str) -> tuple[int, dict[str, np.ndarray]]:
    if variant not in VARIANTS:
        raise DataError(None, f"unknown STG variant {variant!r}; expected one of {VARIANTS}")
    needed = [f for f in ply_fields(variant) if f not in NORMAL_FIELDS]
    missing = [f for f in needed if f not in arrays]
    if missing:
        raise DataError(None, f"model arrays lack the {variant} fields {missing}")
    cols = {f: np.asarray(arrays[f], dtype=np.float64).reshape(-1) for f in needed}
    n = len(cols[needed[0]])
    for f, c in cols.items():
        if len(c) != n:
            raise DataError(None, f"field {f!r} has {len(c)} values, field {needed[0]!r} has {n}")
        bad = int(np.count_nonzero(~np.isfinite(c)))
        if bad:
            raise DataError(None, f"field {f!r} has {bad} non-finite values; refusing to encode")
    if n > MAX_GAUSSIANS:
        raise DataError(None, f"{n} Gaussians exceed the format limit of {MAX_GAUSSIANS}")
    return n, cols


def _compress(raw: bytes, level: int) -> tuple[int, bytes]:
    packed = zstandard.ZstdCompressor(level=level, write_content_size=True, write_checksum=False).compress(raw)
    if len(packed) >= len(raw):
        return CODEC_STORED, raw
    return CODEC_ZSTD, packed


def _stored_dtype(bits: int, flags: int) -> np.dtype:
    """Container of the stored codes: centred codes need one bit more than the quantizer's depth."""
    return container_dtype(bits + 1 if flags & FLAG_CENTRED else bits)


@dataclass(frozen=True)
class _EncodedSection:
    codec: int
    flags: int
    payload: bytes
    raw_size: int
    quantizers: tuple[Quantizer, ...]  # as stored (centring moves each component's centre into its zero point)
    prediction: tuple[int, ...] = ()


def _encode_codes(codes: np.ndarray, bits: int, level: int, adaptive: bool, quantizers: tuple[Quantizer, ...],
                  centrable: bool) -> _EncodedSection:
    """codes [C, N] -> the section. With `adaptive`, the layouts (plain, delta, centred or centred + predicted)
    x (planar or interleaved) are compared and the smallest kept: which wins depends on the data. The comparison
    runs at a fast zstd level (the ranking barely depends on it); only the winner is compressed at `level`."""
    candidates: list[tuple[int, np.ndarray, tuple[Quantizer, ...], tuple[int, ...]]] = [(0, codes, quantizers, ())]
    if adaptive and codes.shape[1] > 1:
        candidates.append((FLAG_DELTA, delta_encode(codes, bits), quantizers, ()))
        if centrable and bits < MAX_BITS:
            centred, centre = centre_encode(codes, bits)
            shifted = tuple(Quantizer(q.step, q.zero_point + int(c), q.bits) for q, c in zip(quantizers, centre))
            candidates.append((FLAG_CENTRED, centred, shifted, ()))
            if codes.shape[0] > 1:
                signed = codes.astype(np.int64) - centre[:, None]
                matrix = fit_prediction(signed)
                if np.any(matrix):
                    residual = zigzag(predict_encode(signed, matrix, bits)).astype(centred.dtype)
                    coefficients = tuple(int(a) for a in matrix[np.tril_indices(len(matrix), -1)])
                    candidates.append((FLAG_CENTRED | FLAG_PREDICT, residual, shifted, coefficients))
    layouts = []
    for flags, stream, stored, prediction in candidates:
        for interleave in ((False, True) if adaptive and codes.shape[0] > 1 else (False,)):
            layouts.append((flags | (FLAG_INTERLEAVE if interleave else 0), to_byte_planes(stream, interleave),
                            stored, prediction))
    if len(layouts) > 1:
        probe = min(level, _PROBE_LEVEL)
        layouts = [min(layouts, key=lambda item: len(_compress(item[1], probe)[1]))]
    flags, raw, stored, prediction = layouts[0]
    codec, payload = _compress(raw, level)
    return _EncodedSection(codec, flags, payload, len(raw), stored, prediction)


def _stored_decoder_dtype(arr: np.ndarray) -> np.dtype:
    """Half precision unless a weight would overflow it (|w| > 65504); then the tensor stays float32."""
    return np.dtype(np.float16) if (arr.size == 0 or np.abs(arr).max() <= _FP16_MAX) else np.dtype(np.float32)


def simulate_decoder_state(state: Mapping[str, Any] | None) -> dict[str, np.ndarray] | None:
    """The decoder weights as `decode` returns them (float32 after the stored precision), without packing."""
    if state is None:
        return None
    out = {}
    for name, value in state.items():
        arr = np.asarray(value.detach().cpu().numpy() if hasattr(value, "detach") else value, dtype=np.float32)
        out[name] = arr.astype(_stored_decoder_dtype(arr)).astype(np.float32)
    return out


def _pack_decoder(state: Mapping[str, Any]) -> bytes:
    """Manifest (name, dtype, shape per tensor) followed by the tensors' little-endian data."""
    head = [struct.pack("<H", len(state))]
    blobs = []
    for name, value in state.items():
        arr = np.asarray(value.detach().cpu().numpy() if hasattr(value, "detach") else value, dtype=np.float32)
        if not np.all(np.isfinite(arr)):
            raise DataError(None, f"decoder tensor {name!r} has non-finite values; refusing to encode")
        dtype = _stored_decoder_dtype(arr)
        key = name.encode("utf-8")
        if len(key) > 0xFFFF or arr.ndim > 8:
            raise DataError(None, f"decoder tensor {name!r} cannot be stored (name too long or ndim > 8)")
        head.append(struct.pack("<H", len(key)) + key + struct.pack("<BB", _DTYPE_CODES[dtype], arr.ndim))
        head.append(struct.pack(f"<{arr.ndim}I", *arr.shape))
        blobs.append(arr.astype(dtype.newbyteorder("<")).tobytes())
    return b"".join(head + blobs)


class QuantizationMemo:
    """What the encoder's quantization gave each attribute group of ONE model's arrays under given settings, kept
    so that calls that differ in a few groups' settings only redo those groups (the rd allocation's trials change
    one group at a time, `stgc.codec.allocation`). Results are the same with or without it. Pass a memo only with
    the arrays it was made for (checked by identity), and do not change those arrays while the memo lives (their
    contents are not checked); it keeps the most recently used CAPACITY results."""

    CAPACITY = 64  # one trial's settings use about 25 results

    def __init__(self, arrays: Mapping[str, np.ndarray]):
        self.arrays = arrays
        self._results: OrderedDict[Hashable, Any] = OrderedDict()

    def get(self, key: Hashable, compute: Callable[[], Any]) -> Any:
        if key in self._results:
            self._results.move_to_end(key)
            return self._results[key]
        value = self._results[key] = compute()
        if len(self._results) > self.CAPACITY:
            self._results.popitem(last=False)
        return value


def _remember(memo: QuantizationMemo | None, key: Hashable, compute: Callable[[], Any]) -> Any:
    return compute() if memo is None else memo.get(key, compute)


def _encoder_columns(arrays: Mapping[str, np.ndarray], variant: str, quality: int,
                     group_bits: Mapping[str, int] | None, step_scales: Mapping[str, Sequence[float]] | None,
                     memo: QuantizationMemo | None = None) -> tuple[int, dict[str, np.ndarray]]:
    """The validated float64 columns the encoder quantizes, rotation and omega canonicalized."""
    if memo is not None and memo.arrays is not arrays:
        raise ValueError("a QuantizationMemo serves only the arrays it was made for")
    n, cols = _remember(memo, ("columns", variant), lambda: _canonical_columns(arrays, variant))
    unknown = (set(group_bits or ()) | set(step_scales or ())) - GROUP_TAGS
    if unknown:
        raise ValueError(f"group_bits/step_scales name unknown groups {sorted(unknown)}")
    for tag_name, factors in (step_scales or {}).items():
        group = GROUP_BY_TAG[tag_name.encode("latin-1")]
        if len(factors) != (3 if group.domain == QUAT_SMALLEST3 else len(group.fields(variant))):
            raise ValueError(f"step_scales[{tag_name!r}] needs one factor per stored component (3 for ROTN)")
    if quality not in QUALITY_LEVELS:
        raise ValueError(f"quality must be one of {QUALITY_LEVELS}, got {quality!r}")
    return n, cols


def _canonical_columns(arrays: Mapping[str, np.ndarray], variant: str) -> tuple[int, dict[str, np.ndarray]]:
    n, cols = _validated_columns(arrays, variant)
    rot = np.stack([cols[f"rot_{i}"] for i in range(4)], axis=1)
    omega = np.stack([cols[f"omega_{i}"] for i in range(4)], axis=1)
    rot, omega = canonical_rotation(rot, omega)
    for i in range(4):
        cols[f"rot_{i}"], cols[f"omega_{i}"] = rot[:, i], omega[:, i]
    return n, cols


def _quantized_groups(cols: dict[str, np.ndarray], n: int, variant: str, quality: int, position_bits: int | None,
                      group_bits: Mapping[str, int] | None, step_scales: Mapping[str, Sequence[float]] | None,
                      outlier_guard: bool, memo: QuantizationMemo | None = None,
                      ) -> Iterator[tuple[AttributeGroup, int, tuple[Quantizer, ...], np.ndarray, np.ndarray, Hashable]]:
    """Per attribute group in GROUPS order: (group, bit depth, quantizers, codes [C, N] in input order, the span
    its TIME_SPAN scaling used, the key of this result). What the encoder stores and what `simulate_quantization`
    reconstructs. A group's result depends on its own settings and, for TIME_SPAN groups, on the span, i.e. on
    TCEN's and TSCL's: `memo` keys it by exactly those."""
    time_groups: dict[bytes, tuple[Hashable, tuple[Quantizer, ...], np.ndarray]] = {}
    span_key: Hashable = None
    span = np.ones(n)
    for group in groups_for(variant):
        tag = group.tag.decode("latin-1")
        bits = bits_for(group, quality)
        if group.tag == b"POSI" and position_bits is not None:
            bits = int(position_bits)
        if group_bits and tag in group_bits:
            bits = int(group_bits[tag])
        container_dtype(bits)  # validates the range
        shape = (step_scales or {}).get(tag)
        key = (variant, tag, bits, None if shape is None else tuple(float(f) for f in shape), outlier_guard,
               span_key if group.domain == TIME_SPAN else None)

        # What a group's depth and steps do not change (its values in the quantized domain, the outlier guard's
        # extra bits) is kept apart, so that the allocation's trials at other settings reuse it.
        values_key: tuple[Hashable, ...] = ("domain", variant, tag, span_key if group.domain == TIME_SPAN else None)

        def domain_values(group: AttributeGroup = group, span: np.ndarray = span) -> np.ndarray:
            values = _to_domain(np.stack([cols[f] for f in group.fields(variant)], axis=0), group.domain)
            return values * _span_factors(group, span) if group.domain == TIME_SPAN else values

        def quantized(group: AttributeGroup = group, bits: int = bits, shape: Sequence[float] | None = shape,
                      values_key: tuple[Hashable, ...] = values_key,
                      domain_values: Callable[[], np.ndarray] = domain_values,
                      ) -> tuple[int, tuple[Quantizer, ...], np.ndarray]:
            values = _remember(memo, values_key, domain_values)
            if group.domain in (LINEAR, TIME_SPAN) and outlier_guard:  # the others are bounded ([0, 1], unit quaternion)
                extra = _remember(memo, ("guard", *values_key), lambda: outlier_guard_extra_bits(values))
                bits = min(MAX_BITS, bits + extra)
            quantizers = _fit_group(values, group.domain, bits, shape)
            return bits, quantizers, np.stack([quantize(v, q) for v, q in zip(values, quantizers)], axis=0)

        bits, quantizers, codes = _remember(memo, key, quantized)
        yield group, bits, quantizers, codes, span, key
        if group.tag in (b"TCEN", b"TSCL"):  # the decoder sees only the quantized values: derive the span from them
            time_groups[group.tag] = (key, quantizers, codes)
            if len(time_groups) == 2:
                (centre_key, centre_q, centre), (scale_key, scale_q, scale) = time_groups[b"TCEN"], time_groups[b"TSCL"]
                span_key = ("span", centre_key, scale_key)
                span = _remember(memo, span_key, lambda: time_span(dequantize(centre[0], centre_q[0]),
                                                                  dequantize(scale[0], scale_q[0])))


@dataclass(frozen=True)
class QuantizedGroup:
    """One attribute group as the encoder quantizes it: codes [C, N] in the input's order (the stored layout, its
    Morton reordering and entropy coding aside), the quantizers that map them back, and, for TIME_SPAN groups,
    the per-Gaussian span the values were scaled by."""

    group: AttributeGroup
    bits: int
    quantizers: tuple[Quantizer, ...]
    codes: np.ndarray
    span: np.ndarray

    @property
    def tag(self) -> str:
        return self.group.tag.decode("latin-1")


def quantized_groups(
    arrays: Mapping[str, np.ndarray],
    variant: str,
    quality: int = DEFAULT_QUALITY,
    *,
    position_bits: int | None = None,
    group_bits: Mapping[str, int] | None = None,
    step_scales: Mapping[str, Sequence[float]] | None = None,
    outlier_guard: bool = True,
    memo: QuantizationMemo | None = None,
) -> list[QuantizedGroup]:
    """Every attribute group's codes as `encode` quantizes them (same options), in GROUPS order: what a rate
    estimate measures (stgc.codec.rate). Positions come first; their codes define the stored Morton order."""
    n, cols = _encoder_columns(arrays, variant, quality, group_bits, step_scales, memo)
    return [QuantizedGroup(group, bits, quantizers, codes, span)
            for group, bits, quantizers, codes, span, _ in _quantized_groups(
                cols, n, variant, quality, position_bits, group_bits, step_scales, outlier_guard, memo)]


def simulate_quantization(
    arrays: Mapping[str, np.ndarray],
    variant: str,
    quality: int = DEFAULT_QUALITY,
    *,
    position_bits: int | None = None,
    group_bits: Mapping[str, int] | None = None,
    step_scales: Mapping[str, Sequence[float]] | None = None,
    outlier_guard: bool = True,
    memo: QuantizationMemo | None = None,
) -> dict[str, np.ndarray]:
    """The attribute arrays `decode(encode(arrays, ...))` returns, in the input's order (encode reorders along the
    Morton curve) and without entropy coding: what a model looks like after the codec, for training that sees it
    (rotation and omega come back canonicalized, which renders the same). Same keyword options as `encode`; `memo`
    (made for these `arrays`) keeps each group's result for later calls."""
    n, cols = _encoder_columns(arrays, variant, quality, group_bits, step_scales, memo)
    out: dict[str, np.ndarray] = {}
    for group, _, quantizers, codes, span, key in _quantized_groups(cols, n, variant, quality, position_bits,
                                                                     group_bits, step_scales, outlier_guard, memo):
        def decoded(group: AttributeGroup = group, quantizers: tuple[Quantizer, ...] = quantizers,
                    codes: np.ndarray = codes, span: np.ndarray = span) -> list[np.ndarray]:
            values = np.stack([dequantize(c, q) for c, q in zip(codes, quantizers)], axis=0)
            if group.domain == TIME_SPAN:
                values = values / _span_factors(group, span)
            return [column.astype(np.float32) for column in _from_domain(values, group.domain)]

        columns = _remember(memo, ("decoded", key), decoded)
        out.update(zip(group.fields(variant), columns if memo is None else (c.copy() for c in columns)))
    return {name: out.get(name, np.zeros(n, np.float32)) for name in ply_fields(variant)}


def _encoded_sections(arrays: Mapping[str, np.ndarray], variant: str, quality: int, *, zstd_level: int = DEFAULT_ZSTD_LEVEL,
                      position_bits: int | None = None, group_bits: Mapping[str, int] | None = None,
                      step_scales: Mapping[str, Sequence[float]] | None = None, adaptive_delta: bool = True,
                      outlier_guard: bool = True, only: str | None = None, memo: QuantizationMemo | None = None,
                      ) -> Iterator[tuple[bytes, int, _EncodedSection]]:
    """(tag, bit depth, entropy-coded section) of every attribute group, in GROUPS order, Gaussians in the Morton
    order of their quantized positions; with `only`, that section alone is entropy-coded and yielded."""
    n, cols = _encoder_columns(arrays, variant, quality, group_bits, step_scales, memo)
    order: np.ndarray | None = None
    for group, bits, quantizers, codes, _, key in _quantized_groups(cols, n, variant, quality, position_bits,
                                                                    group_bits, step_scales, outlier_guard, memo):
        if order is None:  # POSI comes first: its codes define the Morton order used by every section
            order = _remember(memo, ("morton", key), lambda: morton_order(codes.T, bits))
        if only is None or group.tag.decode("latin-1") == only:
            yield group.tag, bits, _encode_codes(codes[:, order], bits, zstd_level, adaptive_delta, quantizers,
                                                 centrable=group.domain != QUAT_SMALLEST3)


def section_payload_bytes(arrays: Mapping[str, np.ndarray], variant: str, tag: str, quality: int = DEFAULT_QUALITY,
                          **options: Any) -> int:
    """The payload bytes `encode` writes for attribute section `tag` (`options`: encode's keyword options but
    metadata, and `memo` as simulate_quantization's), entropy-coding only that section."""
    for _, _, section in _encoded_sections(arrays, variant, quality, only=tag, **options):
        return len(section.payload)
    raise ValueError(f"{variant} models have no attribute section {tag!r}")


def encode(
    arrays: Mapping[str, np.ndarray],
    variant: str,
    decoder_state: Mapping[str, Any] | None = None,
    quality: int = DEFAULT_QUALITY,
    *,
    zstd_level: int = DEFAULT_ZSTD_LEVEL,
    position_bits: int | None = None,
    group_bits: Mapping[str, int] | None = None,
    step_scales: Mapping[str, Sequence[float]] | None = None,
    adaptive_delta: bool = True,
    outlier_guard: bool = True,
    metadata: Mapping[str, Any] | None = None,
) -> bytes:
    """Encode official-layout PLY arrays (float32 [N] per field; normals ignored) into a .stgc bitstream.

    quality 1..5 selects the bit depths (GROUPS); position_bits overrides the position depth, group_bits any
    group's ({"MOTN": 10, ...}, keyed by section tag). step_scales ({"FDC_": [1, 1, 1, 8, 8, 4], ...}) multiplies
    the steps of a group's components by factors >= 1 (one per stored component; ROTN: its three stored ones):
    components whose errors show less get coarser steps at the same depth. outlier_guard adds bits to a linear group whose range
    is stretched by outliers (outlier_guard_extra_bits). The Gaussians are reordered along the Morton curve of their
    quantized positions. metadata: small JSON-able dict kept verbatim."""
    if variant == "full" and decoder_state is None:
        raise DataError(None, "a full-variant model needs its decoder state")
    sections = list(_encoded_sections(arrays, variant, quality, zstd_level=zstd_level, position_bits=position_bits,
                                      group_bits=group_bits, step_scales=step_scales, adaptive_delta=adaptive_delta,
                                      outlier_guard=outlier_guard))  # (tag, bit depth, content); validates arrays
    n = len(np.asarray(arrays["x"]))

    if decoder_state is not None:
        raw = _pack_decoder(decoder_state)
        codec, payload = _compress(raw, zstd_level)
        sections.append((TAG_DECODER, DECODER_BITS, _EncodedSection(codec, 0, payload, len(raw), ())))
    if metadata:
        raw = json.dumps(dict(metadata), sort_keys=True, separators=(",", ":")).encode("utf-8")
        if len(raw) > MAX_META_BYTES:
            raise DataError(None, f"metadata is {len(raw)} bytes; the limit is {MAX_META_BYTES}")
        codec, payload = _compress(raw, zstd_level)
        sections.append((TAG_META, META_BITS, _EncodedSection(codec, 0, payload, len(raw), ())))

    table = bytearray()
    for tag, bits, sec in sections:
        if sec.raw_size > 0xFFFFFFFF:  # the table stores sizes as uint32
            raise DataError(None, f"section {tag.decode()} would hold {sec.raw_size} bytes, beyond the 4 GiB limit")
        table += _ENTRY.pack(tag, sec.codec, bits, len(sec.quantizers), sec.flags, sec.raw_size, len(sec.payload),
                             zlib.crc32(sec.payload))
        for q in sec.quantizers:
            table += _QPARAM.pack(q.step, q.zero_point)
        for a in sec.prediction:
            table += _COEFFICIENT.pack(a)
    head = _HEADER.pack(MAGIC, VERSION, _VARIANT_CODES[variant], quality, n, len(sections), 0, len(table),
                        zlib.crc32(table))
    data = b"".join([head, _HEADER_CRC.pack(zlib.crc32(head)), bytes(table)] + [sec.payload for _, _, sec in sections])
    try:  # what the decoder would refuse is never written (values near the float32 limit overflow a quantizer)
        _check_section_table(read_header(data), None)
    except FormatError as exc:
        raise DataError(None, f"these values cannot be stored: {exc}") from None
    return data


# =====================================================================================================================
# Decoder
# =====================================================================================================================

def _fail(problem: str, source: str | None) -> FormatError:
    return FormatError(source, problem)


def read_header(data: bytes, source: str | None = None) -> StgcHeader:
    """Parse and validate the header and section table (payload checksums are checked by decode)."""
    if len(data) < HEADER_SIZE:
        raise _fail(f"not an .stgc file: {len(data)} bytes is shorter than the {HEADER_SIZE}-byte header", source)
    magic, version, variant_code, quality, n, num_sections, flags, table_size, table_crc = _HEADER.unpack_from(data)
    if magic == VIDEO_MAGIC:
        raise _fail("a whole-video .stgc (one bitstream per segment): read it with stgc.codec.read_video_index / "
                    "read_video_segment, or through stgc eval / render / decompress", source)
    if magic != MAGIC:
        raise _fail("not an .stgc file (bad magic bytes)", source)
    (header_crc,) = _HEADER_CRC.unpack_from(data, _HEADER.size)
    if zlib.crc32(data[: _HEADER.size]) != header_crc:
        raise _fail("header checksum mismatch (file corrupted)", source)
    if version not in READABLE_VERSIONS:
        raise _fail(f"unsupported .stgc version {version} (this reader knows versions {READABLE_VERSIONS})", source)
    if variant_code not in _VARIANT_NAMES:
        raise _fail(f"unknown model variant code {variant_code}", source)
    if quality not in QUALITY_LEVELS:
        raise _fail(f"quality {quality} is outside {QUALITY_LEVELS}", source)
    if n > MAX_GAUSSIANS:
        raise _fail(f"claims {n} Gaussians, above the limit of {MAX_GAUSSIANS}", source)
    if num_sections > MAX_SECTIONS:
        raise _fail(f"claims {num_sections} sections, above the limit of {MAX_SECTIONS}", source)
    if flags != 0:
        raise _fail(f"unknown header flags {flags:#06x}", source)
    if table_size > len(data) - HEADER_SIZE:
        raise _fail(f"section table ({table_size} bytes) runs past the end of the file (truncated?)", source)
    table = data[HEADER_SIZE: HEADER_SIZE + table_size]
    if zlib.crc32(table) != table_crc:
        raise _fail("section table checksum mismatch (file corrupted)", source)

    sections = []
    pos = 0
    for _ in range(num_sections):
        if pos + _ENTRY.size > table_size:
            raise _fail("section table is shorter than its entries", source)
        raw_tag, codec, bits, comps, sflags, raw_size, payload_size, payload_crc = _ENTRY.unpack_from(table, pos)
        tag = raw_tag.decode("latin-1")
        pos += _ENTRY.size
        if pos + comps * _QPARAM.size > table_size:
            raise _fail(f"section {tag!r} quantizer list runs past the section table", source)
        quantizers = []
        for _c in range(comps):
            step, zero_point = _QPARAM.unpack_from(table, pos)
            pos += _QPARAM.size
            quantizers.append(Quantizer(step=step, zero_point=zero_point, bits=bits))
        prediction: tuple[int, ...] = ()
        if sflags & FLAG_PREDICT:
            count = prediction_size(comps)
            if pos + count * _COEFFICIENT.size > table_size:
                raise _fail(f"section {tag!r} prediction coefficients run past the section table", source)
            prediction = struct.unpack_from(f"<{count}h", table, pos)
            pos += count * _COEFFICIENT.size
        sections.append(SectionInfo(tag, codec, bits, comps, sflags, raw_size, payload_size,
                                    payload_crc, tuple(quantizers), prediction))
    if pos != table_size:
        raise _fail(f"section table has {table_size - pos} unexplained trailing bytes", source)
    payload_total = sum(s.payload_size for s in sections)
    if HEADER_SIZE + table_size + payload_total != len(data):
        actual = len(data) - HEADER_SIZE - table_size
        what = "truncated" if actual < payload_total else "has trailing bytes"
        raise _fail(f"file {what}: sections hold {payload_total} payload bytes, file has {actual}", source)
    return StgcHeader(version, _VARIANT_NAMES[variant_code], quality, n, len(data), tuple(sections))


def _check_section(sec: SectionInfo, version: int, source: str | None) -> None:
    allowed = KNOWN_FLAGS if sec.tag in GROUP_TAGS else 0
    if sec.flags & ~allowed:
        raise _fail(f"section {sec.tag!r} has unknown flags {sec.flags:#04x}", source)
    for flag, (name, since) in FLAG_SINCE_VERSION.items():
        if sec.flags & flag and version < since:
            raise _fail(f"section {sec.tag!r} has the {name} flag, new in version {since}, in a version {version} "
                        "file", source)
    if sec.flags & FLAG_CENTRED and (sec.flags & FLAG_DELTA or sec.bits >= MAX_BITS
                                     or GROUP_BY_TAG[sec.tag.encode("latin-1")].domain == QUAT_SMALLEST3):
        raise _fail(f"section {sec.tag!r} combines centring with delta coding, a quaternion group or "
                    f"{sec.bits} bits", source)
    if sec.flags & FLAG_PREDICT and not (sec.flags & FLAG_CENTRED and sec.components > 1):
        raise _fail(f"section {sec.tag!r} is predicted without being centred or with one component", source)
    if sec.codec == CODEC_STORED:
        if sec.raw_size != sec.payload_size:
            raise _fail(f"stored section {sec.tag!r}: raw size {sec.raw_size} != payload {sec.payload_size}", source)
    elif sec.codec == CODEC_ZSTD:
        if sec.raw_size > sec.payload_size * ZSTD_MAX_EXPANSION + ZSTD_SLACK:
            raise _fail(f"section {sec.tag!r} claims {sec.raw_size} bytes from a {sec.payload_size}-byte zstd "
                        "frame, more than zstd can expand", source)
    else:
        raise _fail(f"section {sec.tag!r} uses unknown codec {sec.codec}", source)


def _unpack_payload(data: bytes, offset: int, sec: SectionInfo, source: str | None) -> bytes:
    payload = data[offset: offset + sec.payload_size]
    if zlib.crc32(payload) != sec.payload_crc:
        raise _fail(f"section {sec.tag!r} checksum mismatch (file corrupted)", source)
    if sec.codec == CODEC_STORED:
        return payload
    # Stream in bounded chunks: memory grows only as real content decodes, never past raw_size + 1. The window
    # floor is level 19's default window (8 MiB): a frame written streamed (no content size, so zstd cannot shrink
    # the window to the content) by an ordinary writer must be accepted. Spec §6.
    window = 1 << max(ZSTD_MIN_WINDOW_LOG, min(ZSTD_MAX_WINDOW_LOG, max(sec.raw_size, 1).bit_length()))
    out = bytearray()
    try:
        reader = zstandard.ZstdDecompressor(max_window_size=window).stream_reader(payload)
        while len(out) <= sec.raw_size:
            chunk = reader.read(min(1 << 20, sec.raw_size + 1 - len(out)))
            if not chunk:
                break
            out += chunk
    except zstandard.ZstdError as exc:
        raise _fail(f"section {sec.tag!r} is not a valid zstd frame ({exc})", source) from None
    if len(out) != sec.raw_size:
        raise _fail(f"section {sec.tag!r} decompresses to {len(out)} bytes, expected {sec.raw_size}", source)
    return bytes(out)


def _decode_attribute(raw: bytes, sec: SectionInfo, group: AttributeGroup, n: int, source: str | None,
                      span: np.ndarray | None = None) -> np.ndarray:
    dtype = _stored_dtype(sec.bits, sec.flags)
    codes = from_byte_planes(raw, sec.components, n, dtype, interleave=bool(sec.flags & FLAG_INTERLEAVE))
    if sec.flags & FLAG_DELTA:
        codes = delta_decode(codes, sec.bits)
    elif sec.flags & FLAG_CENTRED:
        if n and int(codes.max()) >= (1 << (sec.bits + 1)):
            raise _fail(f"section {sec.tag!r} holds centred codes beyond its {sec.bits + 1}-bit range", source)
        codes = unzigzag(codes)  # signed, in [-2**bits, 2**bits): the centre is in the quantizer's zero point
        if sec.flags & FLAG_PREDICT:
            codes = predict_decode(codes, sec.prediction_matrix(), sec.bits)  # stays in that range
    elif n and int(codes.max()) >= (1 << sec.bits):
        raise _fail(f"section {sec.tag!r} holds codes beyond its {sec.bits}-bit range", source)
    if group.domain == QUAT_SMALLEST3:
        q = sec.quantizers[3]
        if (q.step, q.zero_point) != (1.0, 0):
            raise _fail(f"section {sec.tag!r}: the quaternion index row must have step 1, zero point 0", source)
        if n and int(codes[3].max()) > 3:
            raise _fail(f"section {sec.tag!r} holds a quaternion component index above 3", source)
    values = np.stack([dequantize(c, q) for c, q in zip(codes, sec.quantizers)], axis=0)
    if group.domain == TIME_SPAN:
        values = values / _span_factors(group, span if span is not None else np.ones(n))
    return _from_domain(values, group.domain)


def _check_quantizers(sec: SectionInfo, group: AttributeGroup, source: str | None) -> None:
    # The codes decoding can give (_decode_attribute): [0, 2**bits) plain or delta coded, [-2**bits, 2**bits)
    # centred (predicted or not). The bound is exact, as version 2's was: a looser one refused version 2 files that
    # version's own decoder read.
    highest = (1 << sec.bits) - 1
    lowest = -(1 << sec.bits) if sec.flags & FLAG_CENTRED else 0
    f32_max = float(np.finfo(np.float32).max)
    if group.domain == TIME_SPAN:  # decoding divides by span**p >= SPAN_MIN**p: the result must still fit
        f32_max *= SPAN_MIN ** max(group.span_powers)
    for q in sec.quantizers:
        if not (np.isfinite(q.step) and q.step > 0):
            raise _fail(f"section {sec.tag!r} has an invalid quantizer step {q.step!r}", source)
        if abs(q.zero_point) > 1 << 53:
            raise _fail(f"section {sec.tag!r} has an absurd quantizer zero point {q.zero_point}", source)
        extreme = max(abs(q.zero_point + lowest), abs(q.zero_point + highest)) * q.step
        if not extreme <= f32_max:
            raise _fail(f"section {sec.tag!r} quantizer reaches {extreme:.3g}, beyond float32", source)


def _unpack_decoder(raw: bytes, source: str | None) -> dict[str, np.ndarray]:
    def need(pos: int, size: int) -> None:
        if pos + size > len(raw):
            raise _fail("decoder section is truncated inside its manifest or data", source)

    need(0, 2)
    (count,) = struct.unpack_from("<H", raw, 0)
    pos = 2
    manifest = []
    for _ in range(count):
        need(pos, 2)
        (name_len,) = struct.unpack_from("<H", raw, pos)
        pos += 2
        need(pos, name_len + 2)
        try:
            name = raw[pos: pos + name_len].decode("utf-8")
        except UnicodeDecodeError:
            raise _fail("decoder tensor name is not UTF-8", source) from None
        pos += name_len
        dtype_code, ndim = struct.unpack_from("<BB", raw, pos)
        pos += 2
        if dtype_code not in _DTYPE_BY_CODE or ndim > 8:
            raise _fail(f"decoder tensor {name!r} has an unknown dtype code {dtype_code} or ndim {ndim}", source)
        need(pos, 4 * ndim)
        shape = struct.unpack_from(f"<{ndim}I", raw, pos)
        pos += 4 * ndim
        manifest.append((name, _DTYPE_BY_CODE[dtype_code], shape))
    state = {}
    for name, dtype, shape in manifest:
        size = int(np.prod(shape, dtype=object)) * dtype.itemsize  # python ints: no overflow on absurd shapes
        need(pos, size)
        arr = np.frombuffer(raw, dtype=dtype.newbyteorder("<"), count=size // dtype.itemsize, offset=pos)
        if not np.all(np.isfinite(arr)):
            raise _fail(f"decoder tensor {name!r} holds non-finite weights", source)
        state[name] = arr.astype(np.float32).reshape(shape)
        pos += size
    if pos != len(raw):
        raise _fail(f"decoder section has {len(raw) - pos} unexplained trailing bytes", source)
    if len(state) != count:
        raise _fail("decoder section repeats a tensor name", source)
    return state


def _parse_metadata(raw: bytes, source: str | None) -> dict[str, Any]:
    try:
        metadata = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise _fail("metadata section is not UTF-8 JSON", source) from None
    if not isinstance(metadata, dict):
        raise _fail("metadata section is not a JSON object", source)
    return metadata


def decode_metadata(data: bytes, source: str | None = None) -> dict[str, Any]:
    """The JSON metadata of a bitstream ({} without one), unpacking no other section: what a caller needs to find
    the run a file belongs to before (or without) decoding its Gaussians."""
    header = read_header(data, source)
    # The whole table, as decode checks it (cheap: nothing is decompressed): its size limits are what keep a
    # crafted META from expanding without bound, and a file decode refuses does not name a run either.
    _check_section_table(header, source)
    offset = HEADER_SIZE + sum(s.table_bytes for s in header.sections)
    for sec in header.sections:
        if sec.tag == _META:
            return _parse_metadata(_unpack_payload(data, offset, sec, source), source)
        offset += sec.payload_size
    return {}


def _check_section_table(header: StgcHeader, source: str | None) -> dict[str, AttributeGroup]:
    """Every rule of the section table (§6) a file must meet before its payloads are read; returns the variant's
    attribute groups by tag. The encoder checks what it wrote with it too."""
    n, variant = header.num_gaussians, header.variant
    expected = {g.tag.decode("latin-1"): g for g in groups_for(variant)}
    seen: set[str] = set()
    for sec in header.sections:
        if sec.tag in seen:
            raise _fail(f"section {sec.tag!r} appears twice", source)
        seen.add(sec.tag)
        _check_section(sec, header.version, source)
        if sec.tag in expected:
            group = expected[sec.tag]
            want = len(group.fields(variant))
            if sec.components != want:
                raise _fail(f"section {sec.tag!r} has {sec.components} components, {variant} needs {want}", source)
            if not MIN_BITS <= sec.bits <= MAX_BITS:
                raise _fail(f"section {sec.tag!r} has an invalid bit depth {sec.bits}", source)
            if sec.raw_size != n * want * _stored_dtype(sec.bits, sec.flags).itemsize:
                raise _fail(f"section {sec.tag!r} size {sec.raw_size} does not match {n} Gaussians", source)
            _check_quantizers(sec, group, source)
        elif sec.tag in (_DECO, _META):
            what, limit, bits = (("decoder", MAX_DECODER_BYTES, DECODER_BITS) if sec.tag == _DECO
                                 else ("metadata", MAX_META_BYTES, META_BITS))
            if sec.raw_size > limit:
                raise _fail(f"{what} section claims {sec.raw_size} bytes, above the limit of {limit}", source)
            if sec.components or sec.bits != bits:
                raise _fail(f"{what} section is malformed ({sec.components} components and bits {sec.bits}; "
                            f"it has 0 and {bits})", source)
        else:
            raise _fail(f"unknown section {sec.tag!r}", source)
    missing = sorted(set(expected) - seen)
    if missing:
        raise _fail(f"{variant} model lacks sections {missing}", source)
    if variant == "full" and _DECO not in seen:
        raise _fail("full-variant model lacks its decoder section", source)
    return expected


def decode(data: bytes | str | os.PathLike, source: str | None = None) -> DecodedModel:
    """Decode a .stgc bitstream (bytes, or a file path). Raises FormatError naming `source` for any invalid input.

    To get a renderable `stgc.model.STGModel`, use `stgc.codec.load_model(path)`."""
    if isinstance(data, (str, os.PathLike)):
        return decode(read_capped(data), source=str(data))
    data = bytes(data)
    header = read_header(data, source)
    n, variant = header.num_gaussians, header.variant
    expected = _check_section_table(header, source)

    columns: dict[str, np.ndarray] = {}
    decoder_state = None
    metadata: dict[str, Any] = {}
    attribute_payloads: dict[str, tuple[bytes, SectionInfo]] = {}
    offset = HEADER_SIZE + sum(s.table_bytes for s in header.sections)
    for sec in header.sections:
        raw = _unpack_payload(data, offset, sec, source)
        offset += sec.payload_size
        if sec.tag in expected:
            attribute_payloads[sec.tag] = (raw, sec)
        elif sec.tag == _DECO:
            decoder_state = _unpack_decoder(raw, source)
        else:
            metadata = _parse_metadata(raw, source)

    # In GROUPS order, whatever the file order: the TIME_SPAN groups need the decoded trbf_center/trbf_scale.
    span = None
    for tag, group in expected.items():
        raw, sec = attribute_payloads[tag]
        values = _decode_attribute(raw, sec, group, n, source, span)
        for name, col in zip(group.fields(variant), values):
            columns[name] = col
        if "trbf_center" in columns and "trbf_scale" in columns and span is None:
            span = time_span(columns["trbf_center"], columns["trbf_scale"])

    arrays = {}
    for name in ply_fields(variant):
        col = columns.get(name)
        arrays[name] = np.zeros(n, np.float32) if col is None else col.astype(np.float32)
    return DecodedModel(arrays, variant, decoder_state, header, metadata)
