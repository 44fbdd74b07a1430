"""Decoding, checking and resampling of images, plus the bounded cache that datasets use."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import cast

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..errors import DataError


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file header, without decoding the pixels."""
    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise DataError(path, "image file is missing") from None
    except (UnidentifiedImageError, OSError) as exc:
        raise DataError(path, f"unreadable image: {exc}") from None


def read_image(path: Path, background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """uint8 RGB [H, W, 3]. Grey, palette and 16-bit images are expanded to 8-bit RGB; images with
    alpha are composited over `background` (RGB in [0, 1]; STG trains on black)."""
    try:
        with Image.open(path) as im:
            im.load()
            # A palette, RGB or grey PNG may carry one transparent colour (its tRNS chunk) instead of an alpha.
            if im.mode in ("RGBA", "LA") or (im.mode in ("P", "RGB", "L") and "transparency" in im.info):
                rgba = np.asarray(im.convert("RGBA"), dtype=np.float32) / 255.0
                alpha = rgba[..., 3:4]
                rgb = rgba[..., :3] * alpha + np.asarray(background, np.float32) * (1.0 - alpha)
                return np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                arr = np.asarray(im, dtype=np.float64)
                arr = np.clip(np.rint(arr / 257.0), 0, 255).astype(np.uint8)
                return np.repeat(arr[..., None], 3, axis=-1)
            return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()
    except FileNotFoundError:
        raise DataError(path, "image file is missing") from None
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise DataError(path, f"unreadable image: {exc}") from None


def resize_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resample uint8 RGB to (width, height).

    Reductions by a whole number that divides both sides use an area average (box filter: each output pixel is
    the exact mean of its block, which keeps pixel-centre geometry and adds no ringing); other sizes, a whole factor
    that leaves a remainder included (1014 / 4), use Lanczos."""
    h, w = image.shape[:2]
    if (w, h) == (width, height):
        return image
    if w % width == 0 and h % height == 0 and w // width == h // height:
        f = w // width
        out = image.reshape(height, f, width, f, 3).astype(np.float32).mean(axis=(1, 3))
        return cast(np.ndarray, np.clip(np.rint(out), 0, 255).astype(np.uint8))
    pil = Image.fromarray(image).resize((width, height), Image.Resampling.LANCZOS)
    return np.asarray(pil, dtype=np.uint8).copy()


class ImageCache:
    """Least-recently-used cache of decoded images, bounded in bytes (thread-safe)."""

    def __init__(self, max_bytes: int):
        self.max_bytes = int(max_bytes)
        self.bytes = 0
        self.hits = 0
        self.misses = 0
        self._items: OrderedDict[object, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: object, load: Callable[[], np.ndarray]) -> np.ndarray:
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                self.hits += 1
                return self._items[key]
        return self.put(key, load())

    def put(self, key: object, image: np.ndarray) -> np.ndarray:
        """Cache `image` under `key` (unless it exceeds the whole budget or the key is taken); returns it."""
        image.setflags(write=False)  # cached arrays are shared: callers must copy to modify
        with self._lock:
            self.misses += 1
            if image.nbytes <= self.max_bytes and key not in self._items:
                self._items[key] = image
                self.bytes += image.nbytes
                while self.bytes > self.max_bytes:
                    _, old = self._items.popitem(last=False)
                    self.bytes -= old.nbytes
        return image

    def peek(self, key: object) -> np.ndarray | None:
        """The cached image for `key`, or None (does not count as a use)."""
        with self._lock:
            return self._items.get(key)

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self.bytes = 0

    def __len__(self) -> int:
        return len(self._items)
