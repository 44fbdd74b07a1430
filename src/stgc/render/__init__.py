"""stgc.render: differentiable 3D Gaussian rasterization behind one function.

    out = rasterize(means, quats, scales, opacities, features, K, viewmat, width, height, background=None,
                    backend="auto")

Backends share the EWA projection's math (gsplat semantics; `projection.py`): "numba" (CPU default, projection and
compositing in numba kernels with hand-written backwards), "torch" (pure PyTorch, any device), "gsplat" (CUDA
kernels, optional). See
docs/rasterizer.md for conventions and measured speed.
"""

from .api import (
    BACKENDS,
    T_MIN,
    RenderOutput,
    available_backends,
    rasterize,
    select_backend,
)
from .projection import ALPHA_MIN, RADIUS_SIGMAS

__all__ = [
    "ALPHA_MIN",
    "BACKENDS",
    "RADIUS_SIGMAS",
    "T_MIN",
    "RenderOutput",
    "available_backends",
    "rasterize",
    "select_backend",
]
