"""What the .stgc codec's attribute sections will cost, without entropy coding them (issue #17).

The encoder stores each attribute group's integer codes in one of a few layouts (plain, delta along the Morton
order, centred with a linear prediction between components) and lets zstd code the smallest. zstd's literals are
Huffman-coded byte planes, so a section costs close to the order-0 entropy of its codes in the layout that wins:
within a few per cent on trained models (benchmarks/rate_estimate.py; tested within 10 %). That entropy is cheap
to compute, and it is what a training-time rate term can be made to follow (stgc.train.quantization.RateTerm):
per component, the code length of each symbol under the model's own histogram.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .format import QUAT_SMALLEST3, QuantizedGroup
from .quantize import MAX_BITS, centre_encode, delta_encode, fit_prediction, morton_order, predict_encode, zigzag


def entropy_bits(symbols: np.ndarray) -> float:
    """Order-0 entropy of each row of `symbols` [C, N] (non-negative integers) times N, summed over the rows: the
    bits an ideal coder with one static model per row spends on them."""
    total = 0.0
    for row in np.atleast_2d(np.asarray(symbols)):
        if row.size == 0:
            continue
        counts = np.bincount(row.astype(np.int64))
        counts = counts[counts > 0].astype(np.float64)
        total += float(-(counts * np.log2(counts / row.size)).sum())
    return total


def byte_plane_bits(stream: np.ndarray, bits: int) -> float:
    """entropy_bits of the bytes zstd's literal coder sees: each row of `stream` [C, N] split into the byte planes
    of its container (codes above 8 bits span two or three bytes, each plane coded on its own), summed. Above 8
    bits this exceeds the symbols' own entropy by what the planes tell about each other."""
    stream = np.asarray(stream, np.int64)
    planes = [(stream >> shift) & 0xFF for shift in range(0, max(bits, 1), 8)]
    return sum(entropy_bits(plane) for plane in planes)


def code_lengths(codes: np.ndarray, levels: int) -> np.ndarray:
    """[levels] bits each code value costs under the histogram of `codes` [N], with one pseudo-count spread over
    the alphabet so that unseen values cost finite (large) lengths; sum over `codes` ~ entropy_bits(codes)."""
    counts = np.bincount(np.asarray(codes, np.int64), minlength=levels)[:levels].astype(np.float64)
    probability = (counts + 1.0 / levels) / (counts.sum() + 1.0)
    return -np.log2(probability)


def section_bits(group: QuantizedGroup, order: np.ndarray) -> float:
    """Estimated payload bits of one section: the order-0 entropy of the smallest layout the encoder considers."""
    codes, bits = group.codes[:, order], group.bits
    candidates = [byte_plane_bits(codes, bits)]
    if codes.shape[1] > 1:
        candidates.append(byte_plane_bits(delta_encode(codes, bits), bits))
        if group.group.domain != QUAT_SMALLEST3 and bits < MAX_BITS:
            centred, centre = centre_encode(codes, bits)
            signed = codes.astype(np.int64) - centre[:, None]
            matrix = fit_prediction(signed) if codes.shape[0] > 1 else np.zeros((1, 1), np.int64)
            if np.any(matrix):
                residual = zigzag(predict_encode(signed, matrix, bits))  # as stored: bits + 1 wide
                candidates.append(byte_plane_bits(residual, bits + 1))
            candidates.append(byte_plane_bits(centred, bits + 1))
    return min(candidates)


def estimate_section_bits(groups: Sequence[QuantizedGroup]) -> dict[str, float]:
    """{section tag: estimated payload bits} of the attribute sections `encode` writes for `groups`
    (`stgc.codec.format.quantized_groups` of the arrays, with encode's options). The decoder and metadata
    sections are not estimated. Every layout is measured along the positions' Morton order, so the POSI group must
    be among `groups`."""
    positions = next((group for group in groups if group.tag == "POSI"), None)
    if positions is None:
        raise ValueError("estimate_section_bits needs the POSI group: the sections are ordered by position")
    order = morton_order(positions.codes.T, positions.bits)
    return {group.tag: section_bits(group, order) for group in groups}
