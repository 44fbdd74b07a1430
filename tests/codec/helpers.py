"""Shared helpers for the codec tests."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from stgc.codec.format import DecodedModel


def match_rows(original: dict[str, np.ndarray], decoded: dict[str, np.ndarray]) -> np.ndarray:
    """index such that decoded row index[i] is original row i, found by nearest neighbour in a standardized
    attribute space (independent of the codec's own Morton ordering). Asserts it is a permutation."""
    keys = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "scale_0", "scale_1", "scale_2", "trbf_center"]
    a = np.stack([original[k].astype(np.float64) for k in keys], axis=1)
    b = np.stack([decoded[k].astype(np.float64) for k in keys], axis=1)
    scale = a.std(axis=0) + 1e-12
    _, index = cKDTree(b / scale).query(a / scale)
    assert len(np.unique(index)) == len(index), "decoded rows do not map one-to-one onto the originals"
    return index


def steps(decoded: DecodedModel) -> dict[str, list[float]]:
    """Quantizer step per component, by section tag."""
    return {s.tag: [q.step for q in s.quantizers] for s in decoded.header.sections}


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x.astype(np.float64)))


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2)))
