"""The one canonical camera record used everywhere in stgc.

Convention: OpenCV pinhole. World-to-camera `w2c` maps world points to camera coordinates with
x right, y down, z forward (looking along +z). `K` is the 3x3 intrinsic matrix in pixels where the
centre of the top-left pixel is at (0.5, 0.5) (the 3DGS/gsplat convention: a pixel (u, v) integer
index has its centre at (u + 0.5, v + 0.5)).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np


@dataclass(frozen=True, eq=False)
class Camera:
    """One view of one frame.

    name:   camera identifier as the dataset names it ("cam00", "v06", "3").
    frame:  absolute frame index in the source video.
    time:   normalised time of the frame within its segment, t = (frame - start) / duration.
    K:      float64 [3, 3] intrinsics.
    w2c:    float64 [4, 4] world-to-camera (OpenCV).
    width, height: image size in pixels (after any downscale).
    image:  where the pixels come from: a file path, or a callable returning uint8 [H, W, 3].
    """

    name: str
    frame: int
    time: float
    K: np.ndarray
    w2c: np.ndarray
    width: int
    height: int
    image: Path | Callable[[], np.ndarray] | None = field(default=None, repr=False)

    @property
    def c2w(self) -> np.ndarray:
        return np.linalg.inv(self.w2c)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        R, t = self.w2c[:3, :3], self.w2c[:3, 3]
        return -R.T @ t

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by `factor` (pixel-centre preserving)."""
        K = self.K.copy()
        K[:2, :] *= factor
        return replace(
            self,
            K=K,
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
        )
