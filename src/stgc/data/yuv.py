"""Planar YUV 4:2:0 files (MPEG immersive video sequences): read, write, BT.709 colour conversion.

Layout per frame: Y plane (W·H samples), then Cb and Cr planes (W/2·H/2 each). 8-bit files store one
byte per sample; 10-bit files ("yuv420p10le") store each sample in a little-endian uint16.
Colour: BT.709 (Kr = 0.2126, Kb = 0.0722). "limited" (video) range puts Y in [16, 235]·2^(n−8) and
chroma in [16, 240]·2^(n−8); "full" range uses [0, 2^n − 1]. Chroma is upsampled by repeating each
sample over its 2×2 block (exact for images whose colour is constant over 2×2 blocks).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..fileio import atomic_open

log = logging.getLogger(__name__)

KR, KB = 0.2126, 0.0722
KG = 1.0 - KR - KB


def frame_bytes(width: int, height: int, bit_depth: int) -> int:
    """Bytes of one 4:2:0 frame (chroma planes of ceil(W/2) x ceil(H/2))."""
    cw, ch = (width + 1) // 2, (height + 1) // 2
    return (width * height + 2 * cw * ch) * (2 if bit_depth > 8 else 1)


def _levels(bit_depth: int, color_range: str) -> tuple[float, float, float, float]:
    """(luma offset, luma span, chroma centre, chroma span) in code values."""
    scale = float(1 << (bit_depth - 8))
    if color_range == "limited":
        return 16 * scale, 219 * scale, 128 * scale, 224 * scale
    if color_range == "full":
        top = float((1 << bit_depth) - 1)
        return 0.0, top, float(1 << (bit_depth - 1)), top
    raise ValueError(f"color_range must be 'limited' or 'full', not {color_range!r}")


def rgb_to_yuv420(rgb: np.ndarray, bit_depth: int = 10,
                  color_range: str = "limited") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """uint8 or [0,1] float RGB [H, W, 3] -> integer planes (Y [H,W], Cb, Cr [ceil(H/2), ceil(W/2)]).

    Chroma is the mean over each 2x2 block (edge blocks padded by replication)."""
    x = rgb.astype(np.float64) / 255.0 if rgb.dtype == np.uint8 else rgb.astype(np.float64)
    y = KR * x[..., 0] + KG * x[..., 1] + KB * x[..., 2]
    pb = (x[..., 2] - y) / (2 * (1 - KB))
    pr = (x[..., 0] - y) / (2 * (1 - KR))
    h, w = y.shape
    pad = ((0, h % 2), (0, w % 2))
    pb = np.pad(pb, pad, mode="edge")
    pr = np.pad(pr, pad, mode="edge")
    pb = pb.reshape(pb.shape[0] // 2, 2, pb.shape[1] // 2, 2).mean(axis=(1, 3))
    pr = pr.reshape(pr.shape[0] // 2, 2, pr.shape[1] // 2, 2).mean(axis=(1, 3))
    y0, ys, c0, cs = _levels(bit_depth, color_range)
    top = (1 << bit_depth) - 1
    dtype = np.uint16 if bit_depth > 8 else np.uint8
    Y = np.clip(np.rint(y0 + ys * y), 0, top).astype(dtype)
    U = np.clip(np.rint(c0 + cs * pb), 0, top).astype(dtype)
    V = np.clip(np.rint(c0 + cs * pr), 0, top).astype(dtype)
    return Y, U, V


def yuv420_to_rgb(Y: np.ndarray, U: np.ndarray, V: np.ndarray, bit_depth: int = 10,
                  color_range: str = "limited") -> np.ndarray:
    """Integer planes -> uint8 RGB [H, W, 3] (BT.709, chroma repeated over 2x2 blocks)."""
    y0, ys, c0, cs = _levels(bit_depth, color_range)
    h, w = Y.shape
    y = (Y.astype(np.float64) - y0) / ys
    pb = np.repeat(np.repeat((U.astype(np.float64) - c0) / cs, 2, 0), 2, 1)[:h, :w]
    pr = np.repeat(np.repeat((V.astype(np.float64) - c0) / cs, 2, 0), 2, 1)[:h, :w]
    r = y + 2 * (1 - KR) * pr
    b = y + 2 * (1 - KB) * pb
    g = (y - KR * r - KB * b) / KG
    rgb = np.stack([r, g, b], axis=-1)
    return np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)


def bit_depth_from_name(path: Path) -> int | None:
    """10 for names like 'v00_texture_1920x1080_yuv420p10le.yuv', 8 for '..._yuv420p.yuv', else None."""
    name = path.name.lower()
    match = re.search(r"(?:p|_)(1[0-6]|9)(?:le|bit|b)?(?:[._]|$)", name)
    if match:
        return int(match.group(1))
    if re.search(r"yuv420p(?:[._]|$)", name) or "8bit" in name:
        return 8
    return None


def detect_bit_depth(path: Path, width: int, height: int, declared: int | None = None,
                     frames: int | None = None) -> int:
    """Bit depth of a 4:2:0 file: `declared` (the sequence JSON's BitDepthColor), else its name, else its size and
    content. The declaration wins over the name, whose pattern can misread a name ("A_10_texture.yuv"); where the
    two disagree a warning says so.

    From the size alone, a file of 2n 8-bit frames looks like n 10-bit frames; then the content
    decides: 10-bit little-endian samples never have a high byte above 3, which random 8-bit
    video bytes almost always do."""
    from_name = bit_depth_from_name(path)
    if declared is not None:
        if from_name is not None and from_name != int(declared):
            log.warning("%s: the name reads as %d-bit but the sequence declares BitDepthColor %d; using %d",
                        path, from_name, int(declared), int(declared))
        return int(declared)
    if from_name is not None:
        return from_name
    size = path.stat().st_size
    fits = [d for d in (8, 10) if size > 0 and size % frame_bytes(width, height, d) == 0]
    if frames is not None:
        fits = [d for d in fits if size // frame_bytes(width, height, d) >= frames]
    if not fits:
        raise DataError(path, f"file size {size} B is not a whole number of {width}x{height} 4:2:0 frames "
                              "at 8 or 10 bits")
    if len(fits) == 1:
        return fits[0]
    sample = np.fromfile(path, dtype=np.uint8, count=min(size, 1 << 20))
    return 10 if int(sample[1::2].max()) <= 3 else 8


def count_frames(path: Path, width: int, height: int, bit_depth: int) -> int:
    size = path.stat().st_size
    per_frame = frame_bytes(width, height, bit_depth)
    if size % per_frame:
        raise DataError(path, f"file size {size} B is not a whole number of {width}x{height} "
                              f"{bit_depth}-bit 4:2:0 frames ({per_frame} B each)")
    return size // per_frame


def read_frame(path: Path, width: int, height: int, index: int, bit_depth: int,
               color_range: str = "limited") -> np.ndarray:
    """Frame `index` (0-based, within the file) of a planar 4:2:0 file as uint8 RGB."""
    per_frame = frame_bytes(width, height, bit_depth)
    dtype = np.dtype("<u2") if bit_depth > 8 else np.dtype("u1")
    count = per_frame // dtype.itemsize
    try:
        data = np.fromfile(path, dtype=dtype, count=count, offset=index * per_frame)
    except OSError as exc:
        raise DataError(path, f"cannot read YUV frame {index}: {exc}") from None
    if data.size != count:
        raise DataError(path, f"file ends before frame {index} ({width}x{height}, {bit_depth}-bit 4:2:0)")
    cw, ch = (width + 1) // 2, (height + 1) // 2
    Y = data[: width * height].reshape(height, width)
    U = data[width * height : width * height + cw * ch].reshape(ch, cw)
    V = data[width * height + cw * ch :].reshape(ch, cw)
    if bit_depth > 8 and int(max(Y.max(), U.max(), V.max())) >= (1 << bit_depth):
        raise DataError(path, f"sample values exceed {bit_depth} bits: wrong bit depth or not a YUV file")
    return yuv420_to_rgb(Y, U, V, bit_depth, color_range)


def write_yuv420(path: str | Path, frames: list[np.ndarray] | np.ndarray, bit_depth: int = 10,
                 color_range: str = "limited") -> None:
    """Write RGB frames [H, W, 3] as one planar 4:2:0 file (atomically)."""
    with atomic_open(path, "wb") as f:
        for rgb in frames:
            for plane in rgb_to_yuv420(np.asarray(rgb), bit_depth, color_range):
                f.write(plane.astype("<u2" if bit_depth > 8 else "u1").tobytes())
