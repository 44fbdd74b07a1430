"""Numeric building blocks of the .stgc codec: uniform quantizer, Morton order, delta/zigzag, byte planes.

Everything here is pure numpy and knows nothing of files; `format.py` assembles it into a bitstream.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MIN_BITS = 2  # one bit leaves no room for the zero-snapping slack level
MAX_BITS = 24


@dataclass(frozen=True)
class Quantizer:
    """Uniform scalar quantizer of one component: value = (code + zero_point) * step.

    The grid is anchored at integer multiples of `step`, so 0.0 is reproduced exactly whenever the fitted
    range contains it (static Gaussians keep motion/omega exactly 0 instead of drifting by half a step)."""

    step: float
    zero_point: int
    bits: int

    @property
    def levels(self) -> int:
        return 1 << self.bits

    @property
    def max_error(self) -> float:
        """Largest reconstruction error for any input inside the fitted range (before the float32 cast)."""
        return 0.5 * self.step


def container_dtype(bits: int) -> np.dtype:
    """Smallest unsigned integer type holding `bits`-bit codes."""
    if not MIN_BITS <= bits <= MAX_BITS:
        raise ValueError(f"bit depth must be in {MIN_BITS}..{MAX_BITS}, got {bits}")
    return np.dtype(np.uint8 if bits <= 8 else np.uint16 if bits <= 16 else np.uint32)


def fit_quantizer(values: np.ndarray, bits: int, coarsen: float = 1.0) -> Quantizer:
    """Quantizer covering [min, max] of `values` (finite) with 2**bits levels.

    step = (max - min) / (2**bits - 2): one level of slack pays for snapping the grid origin to a multiple of
    step (zero_point = floor(min / step)); then every code fits in `bits` bits and |error| <= step / 2.
    `coarsen` >= 1 multiplies the step (the codes then use fewer than 2**bits levels, so they still fit): an
    encoder spends fewer bits on a component whose errors matter less than its group's others."""
    container_dtype(bits)
    if not (math.isfinite(coarsen) and coarsen >= 1.0):
        raise ValueError(f"coarsen must be a finite factor >= 1, got {coarsen!r}")
    lo = float(np.min(values)) if values.size else 0.0
    hi = float(np.max(values)) if values.size else 0.0
    if hi > lo:
        # At least 2**-52 of the values' magnitude: a span of a few float64 ulps (opacity logits far out, where the
        # sigmoid is 1 - 1e-16) would otherwise give a zero point beyond the 2**53 the format allows.
        step = max((hi - lo) / ((1 << bits) - 2) * coarsen, max(abs(lo), abs(hi)) * 2.0**-52)
        return Quantizer(step=step, zero_point=int(np.floor(lo / step)), bits=bits)
    # Constant component: the constant itself is represented exactly as (+-1) * step.
    step = abs(lo) if lo != 0.0 else 1.0
    return Quantizer(step=step, zero_point=int(np.sign(lo)), bits=bits)


def quantize(values: np.ndarray, q: Quantizer) -> np.ndarray:
    """Codes in [0, 2**bits) (values outside the fitted range are clamped)."""
    codes = np.rint(values.astype(np.float64) / q.step) - q.zero_point
    np.clip(codes, 0, q.levels - 1, out=codes)
    return codes.astype(container_dtype(q.bits))


def dequantize(codes: np.ndarray, q: Quantizer) -> np.ndarray:
    """float64 reconstruction; (code + zero_point) is an exact integer, so a zero on the grid comes back as 0.0."""
    return (codes.astype(np.int64) + q.zero_point).astype(np.float64) * q.step


# --- Morton (Z-order) -------------------------------------------------------------------------------------------

def _spread_bits_21(v: np.ndarray) -> np.ndarray:
    """Insert two zero bits between each of the low 21 bits of v (uint64)."""
    v = v & np.uint64(0x1FFFFF)
    v = (v | (v << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    v = (v | (v << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    v = (v | (v << np.uint64(2))) & np.uint64(0x1249249249249249)
    return v


def morton_codes(grid: np.ndarray, bits: int) -> np.ndarray:
    """63-bit Morton codes of integer grid coordinates [N,3] with `bits` bits per axis (top 21 bits used)."""
    shift = np.uint64(max(bits - 21, 0))
    g = grid.astype(np.uint64) >> shift
    return _spread_bits_21(g[:, 0]) | (_spread_bits_21(g[:, 1]) << np.uint64(1)) | (
        _spread_bits_21(g[:, 2]) << np.uint64(2))


def morton_order(grid: np.ndarray, bits: int) -> np.ndarray:
    """Permutation sorting points along the Z-order curve (stable, so ties keep their input order)."""
    return np.argsort(morton_codes(grid, bits), kind="stable")


# --- delta + zigzag along the stored order ------------------------------------------------------------------------

def delta_encode(codes: np.ndarray, bits: int) -> np.ndarray:
    """Per-row differences modulo 2**bits, zigzag-mapped so small steps of either sign become small codes.

    `codes` is [C, N]; each row is coded independently; the first element is kept as is."""
    modulus = np.int64(1) << np.int64(bits)
    c = codes.astype(np.int64)
    d = np.empty_like(c)
    d[:, :1] = c[:, :1]
    np.subtract(c[:, 1:], c[:, :-1], out=d[:, 1:])
    d %= modulus
    signed = np.where(d >= modulus // 2, d - modulus, d)  # in [-2**(b-1), 2**(b-1))
    zig = np.where(signed >= 0, 2 * signed, -2 * signed - 1)
    return zig.astype(codes.dtype)


def delta_decode(zig: np.ndarray, bits: int) -> np.ndarray:
    """Inverse of delta_encode; any input (even corrupted) yields codes in [0, 2**bits)."""
    modulus = np.int64(1) << np.int64(bits)
    z = zig.astype(np.int64)
    signed = np.where(z & 1, -(z >> 1) - 1, z >> 1)
    out = np.cumsum(signed, axis=1) % modulus
    return out.astype(zig.dtype)


# --- centring: signed offsets from a per-component centre code ------------------------------------------------------

def zigzag(signed: np.ndarray) -> np.ndarray:
    """Signed integers -> non-negative (0, -1, 1, -2, ... -> 0, 1, 2, 3, ...), int64."""
    s = signed.astype(np.int64)
    return np.where(s >= 0, 2 * s, -2 * s - 1)


def unzigzag(zig: np.ndarray) -> np.ndarray:
    z = zig.astype(np.int64)
    return np.where(z & 1, -(z >> 1) - 1, z >> 1)


def centre_encode(codes: np.ndarray, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """[C, N] codes -> (zigzag(code - centre) in a (bits+1)-bit container, centre [C] = each row's median code).

    Byte-oriented coders see one symbol alphabet for all components of a section; centring puts every component's
    bulk on the same small symbols, so their mixture is as compressible as each alone (for attributes that peak
    at a different code per component, e.g. motion coefficients, whose 0.0 sits at a different code in each)."""
    c = codes.astype(np.int64)
    centre = np.zeros(c.shape[0], np.int64)
    if c.shape[1]:
        centre = np.asarray(np.median(c, axis=1)).round().astype(np.int64)
    return zigzag(c - centre[:, None]).astype(container_dtype(bits + 1)), centre


# --- prediction: each component from the ones before it -------------------------------------------------------------

PREDICTION_SHIFT = 8  # prediction coefficients are integers in units of 2**-8
_COEFFICIENT_LIMIT = (1 << 15) - 1  # they are stored as int16


def prediction_size(components: int) -> int:
    """Number of coefficients of a [C, C] strictly lower-triangular prediction matrix."""
    return components * (components - 1) // 2


def _predicted(signed: np.ndarray, coefficients: np.ndarray, row: int) -> np.ndarray:
    """Integer prediction of row `row` from rows 0..row-1: floor((sum_k a_k s_k + 2**(P-1)) / 2**P)."""
    acc = np.zeros(signed.shape[1], np.int64)
    for k in range(row):
        if coefficients[row, k]:
            acc += np.int64(coefficients[row, k]) * signed[k]
    return (acc + (1 << (PREDICTION_SHIFT - 1))) >> PREDICTION_SHIFT


def _wrap(values: np.ndarray, bits: int) -> np.ndarray:
    """Into [-2**bits, 2**bits) modulo 2**(bits+1): the range of a centred code, so residuals need no extra bit."""
    half = np.int64(1) << np.int64(bits)
    return (values + half) % (2 * half) - half


def fit_prediction(signed: np.ndarray) -> np.ndarray:
    """[C, C] int64 strictly lower-triangular coefficients (units of 2**-PREDICTION_SHIFT) predicting each row of
    the centred codes `signed` [C, N] linearly from the rows before it (least squares). A row whose prediction
    would not shrink its residuals (sum of absolute values) keeps coefficients 0."""
    c, n = signed.shape
    coefficients = np.zeros((c, c), np.int64)
    values = signed.astype(np.float64)
    for row in range(1, c):
        if n < 2:
            break
        solution, *_ = np.linalg.lstsq(values[:row].T, values[row], rcond=None)
        scaled = np.clip(np.rint(solution * (1 << PREDICTION_SHIFT)), -_COEFFICIENT_LIMIT, _COEFFICIENT_LIMIT)
        coefficients[row, :row] = scaled.astype(np.int64)
        residual = signed[row] - _predicted(signed, coefficients, row)
        if np.abs(residual).sum() >= np.abs(signed[row].astype(np.int64)).sum():
            coefficients[row, :row] = 0
    return coefficients


def predict_encode(signed: np.ndarray, coefficients: np.ndarray, bits: int) -> np.ndarray:
    """Centred codes [C, N] in [-2**bits, 2**bits) -> residuals (same range): each row minus its prediction from
    the rows before it, wrapped modulo 2**(bits+1)."""
    s = signed.astype(np.int64)
    out = np.empty_like(s)
    for row in range(s.shape[0]):
        out[row] = _wrap(s[row] - _predicted(s, coefficients, row), bits)
    return out


def predict_decode(residual: np.ndarray, coefficients: np.ndarray, bits: int) -> np.ndarray:
    """Inverse of predict_encode; any input (even corrupted) gives rows in [-2**bits, 2**bits)."""
    r = residual.astype(np.int64)
    out = np.empty_like(r)
    for row in range(r.shape[0]):
        out[row] = _wrap(r[row] + _predicted(out, coefficients, row), bits)
    return out


# --- byte planes ----------------------------------------------------------------------------------------------------

def to_byte_planes(codes: np.ndarray, interleave: bool = False) -> bytes:
    """[C, N] unsigned ints -> bytes, split into byte planes (all low bytes, then the next byte, ...).

    Planar (default): ordered (component, byte significance, gaussian), i.e. each component's planes in turn.
    Interleaved: ordered (byte significance, gaussian, component), i.e. a Gaussian's components side by side,
    which lets zstd match whole rows (a static Gaussian's 9 motion codes are the same row every time).
    Separating planes lets zstd see the nearly constant high bytes as long runs."""
    c, n = codes.shape
    width = codes.dtype.itemsize
    le = np.ascontiguousarray(codes, dtype=codes.dtype.newbyteorder("<"))
    planes = le.view(np.uint8).reshape(c, n, width)
    planes = planes.transpose(2, 1, 0) if interleave else planes.transpose(0, 2, 1)
    return np.ascontiguousarray(planes).tobytes()


def from_byte_planes(raw: bytes, components: int, n: int, dtype: np.dtype, interleave: bool = False) -> np.ndarray:
    """Inverse of to_byte_planes; len(raw) must equal components * n * itemsize (the caller checks)."""
    width = dtype.itemsize
    flat = np.frombuffer(raw, dtype=np.uint8)
    if interleave:
        per_gaussian = flat.reshape(width, n, components).transpose(2, 1, 0)
    else:
        per_gaussian = flat.reshape(components, width, n).transpose(0, 2, 1)
    le = np.ascontiguousarray(per_gaussian).view(dtype.newbyteorder("<"))
    return le.reshape(components, n).astype(dtype, copy=False)
