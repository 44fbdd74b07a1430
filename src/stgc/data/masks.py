"""Foreground masks shipped with a capture (Panoptic `seg/`), and initial points for the moving subjects from them.

A real multi-camera capture triangulates well on its textured static surroundings and hardly at all on the people
in it (they move, wear plain clothes and fill few pixels). Where the data has foreground masks, the visual hull
(the voxels whose projection falls inside the mask of every camera that sees them) is a coarse but complete shape
of the subjects at each frame; its voxels give the initial points for them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..errors import DataError
from .cameras import Camera

# A pixel is foreground when its (resampled) mask value is at least this (0-255 masks; 0/255 in Panoptic).
FOREGROUND_LEVEL = 128


def read_mask(path: Path, width: int, height: int) -> np.ndarray:
    """bool [height, width]: the foreground of the mask image at `path`, area-averaged to the camera's size when it
    is larger with the same aspect (the downscaled dataset), bilinearly enlarged when it is smaller with the same
    aspect (a downscale below 1, or masks stored smaller than their images), else a DataError naming the file.

    Read as 0 (background) .. 255 (foreground): a 1-bit or 0/255 greyscale mask as stored; a palette ('P') mask of
    colours by its indices (0 background, any other foreground, whatever their colours: DAVIS-style masks give
    index 1 a dark colour), one whose colours in use are all grey by its grey level (Pillow's own quantize of a
    black and white mask may put white at index 0); a greyscale mask whose largest value is 1 as a 0/1 mask
    (Dynamic 3D Gaussians' seg values). The colour palettes and 0/1 masks were read through their grey level, so
    every pixel fell below FOREGROUND_LEVEL and the mask was all background."""
    try:
        with Image.open(path) as im:
            im.load()
            if im.mode == "P" and not _grey_palette(im):
                mask = np.where(np.asarray(im) != 0, 255.0, 0.0).astype(np.float32)
            else:
                mask = np.asarray(im.convert("L"), dtype=np.float32)
                # A 0/1 mask, not a threshold at half the file's own maximum: that would also change masks that
                # hold a 255 scale (soft edges, a faint one whose maximum is low, compression noise in an empty
                # one read as foreground), while a maximum of 1 can only be a 0/1 mask: on the 0..255 scale it
                # was all background. 0/255 and 1-bit masks (maximum 0 or 255) read exactly as before.
                if mask.max(initial=0.0) == 1.0:
                    mask *= 255.0
    except FileNotFoundError:
        raise DataError(path, "mask file is missing") from None
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise DataError(path, f"unreadable mask: {exc}") from None
    h, w = mask.shape
    if (w, h) != (width, height):
        f = w // width if width else 0
        if f >= 1 and w == f * width and h == f * height:
            mask = mask.reshape(height, f, width, f).mean(axis=(1, 3))
        elif width and height and w > width and abs(h * width / w - height) <= 1:
            # a downscale by a factor that is not whole: area-averaged over the same box as the image's pixels
            mask = np.asarray(Image.fromarray(mask, mode="F").resize((width, height), Image.Resampling.BOX))
        elif width and height and w < width and abs(h * width / w - height) <= 1:
            # an upscale (downscale < 1): bilinear, not nearest, since the threshold below then puts the edge on the
            # interpolated half-way contour (where the mask's own edge lies, to a fraction of its pixel) instead of
            # a staircase of enlarged mask pixels; PIL maps pixel centres, as the images' resampling does.
            mask = np.asarray(Image.fromarray(mask, mode="F").resize((width, height), Image.Resampling.BILINEAR))
        else:
            raise DataError(path, f"mask is {w}x{h} but its image is {width}x{height} (masks must have the "
                            "images' full size or their aspect at another size)")
    return mask >= FOREGROUND_LEVEL


def _grey_palette(image: Image.Image) -> bool:
    """Whether every palette entry the image uses is a grey (r == g == b)."""
    palette = np.asarray(image.getpalette() or [], dtype=np.int64)
    colours = palette[: len(palette) // 3 * 3].reshape(-1, 3)
    used = np.unique(np.asarray(image))
    used = used[used < len(colours)]
    return bool(np.all(colours[used, 0] == colours[used, 1]) and np.all(colours[used, 1] == colours[used, 2]))


def visual_hull(cameras: list[Camera], masks: list[np.ndarray], lower: np.ndarray, upper: np.ndarray,
                resolution: int = 96, min_views: int = 2, misses_allowed: int = 1) -> np.ndarray:
    """Centres [M, 3] of the voxels of the box [lower, upper] (cubes of side max extent / resolution) that at least
    `min_views` cameras see and that fall inside the foreground of every one of them but `misses_allowed`
    (a tolerance for mask noise and calibration error); min_views must exceed misses_allowed."""
    if min_views <= misses_allowed:
        raise ValueError("min_views must exceed misses_allowed, or voxels no mask covers would be kept")
    lower, upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
    side = float((upper - lower).max()) / resolution
    axes = [np.arange(lo + side / 2, hi, side) for lo, hi in zip(lower, upper)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    seen = np.zeros(len(grid), np.int32)
    inside = np.zeros(len(grid), np.int32)
    for camera, mask in zip(cameras, masks):
        uv, depth = camera.project(grid)
        u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        visible = (depth > camera.near) & (u >= 0) & (v >= 0) & (u < camera.width) & (v < camera.height)
        seen += visible
        hit = np.zeros(len(grid), bool)
        hit[visible] = mask[v[visible], u[visible]]
        inside += hit
    keep = (seen >= min_views) & (inside >= seen - misses_allowed)
    return grid[keep]


def hull_colours(points: np.ndarray, cameras: list[Camera], images: list[np.ndarray],
                 masks: list[np.ndarray]) -> np.ndarray:
    """float [M, 3] in [0, 1]: the mean colour of each point's projections that land on foreground pixels."""
    total = np.zeros((len(points), 3))
    count = np.zeros(len(points))
    for camera, image, mask in zip(cameras, images, masks):
        uv, depth = camera.project(points)
        u, v = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        ok = (depth > camera.near) & (u >= 0) & (v >= 0) & (u < camera.width) & (v < camera.height)
        ok[ok] &= mask[v[ok], u[ok]]
        total[ok] += image[v[ok], u[ok], :3] / 255.0
        count[ok] += 1
    return (total / np.maximum(count, 1)[:, None]).astype(np.float32)
