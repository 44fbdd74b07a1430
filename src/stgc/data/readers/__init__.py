"""Readers for multi-view video layouts; each returns a `SourceScene` that `assemble` turns into a `Dataset`.

Pixel conventions of the intrinsics (ours: top-left pixel centre at (0.5, 0.5)):
- Panoptic / Dynamic3DGaussians: OpenCV convention (centre at (0, 0)) -> cx + 0.5, cy + 0.5.
- Blender / D-NeRF: cx = W/2 is the image centre in our convention already -> unchanged.
- N3DV / LLFF: only a focal length; principal point at the image centre (W/2, H/2).
- COLMAP (STG preprocessed) and Technicolor (fed to COLMAP unchanged by STG): COLMAP's convention = ours.
- MPEG immersive video: Principle_point is taken as given (image centre = W/2 for a centred camera).
"""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path

from ...errors import DataError
from ..dataset import DEFAULT_CACHE_BYTES, Dataset, assemble
from .registry import (
    READERS,
    Reader,
    ReaderOptions,
    format_names,
    readers_in_order,
    register_reader,
    resolve_format,
)


def _load_builtin_readers() -> None:
    """Import every module of this package: each registers its reader."""
    for module in pkgutil.iter_modules(__path__):
        if not module.name.startswith("_") and module.name != "registry":
            importlib.import_module(f"{__name__}.{module.name}")


_load_builtin_readers()


def open_dataset(path: str | Path, format: str = "auto", downscale: float = 1, start: int | None = None,
                 duration: int | None = None, test_cameras: list[str] | str | None = None,
                 fps: float | None = None, *, image_cache_mb: int = DEFAULT_CACHE_BYTES >> 20,
                 background: str | tuple[float, float, float] = "black", yuv_range: str = "limited",
                 check_images: bool = True, near_plane: float | None = None) -> Dataset:
    """Open a multi-view video dataset, picking the reader from the files present (or `format=`).

    start/duration select frames [start, start + duration) (default: everything); test_cameras
    overrides the format's held-out views; fps overrides the format's frame rate (default 30).
    background ("black", "white" or RGB in [0, 1]) is what RGBA images are composited on; decoded
    images are kept in an LRU cache of at most image_cache_mb MiB. near_plane overrides the format's culling
    depth (`SourceScene.near_plane`)."""
    path = Path(path)
    if not path.exists():
        raise DataError(path, "dataset path does not exist")
    path = path.resolve()
    fmt = detect_format(path) if format == "auto" else resolve_format(format)
    if fmt is None:
        raise DataError(path, f"unknown format {format!r}; choose one of {', '.join(format_names())} or 'auto'")
    scene = READERS[fmt].read(path, ReaderOptions(yuv_range=yuv_range))
    return assemble(scene, downscale=downscale, start=start, duration=duration, test_cameras=test_cameras,
                    fps=fps, cache_bytes=int(image_cache_mb) << 20, background=_background(background),
                    check_images=check_images, near_plane=near_plane)


def _background(value: str | tuple[float, float, float]) -> tuple[float, float, float]:
    named = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}
    if isinstance(value, str):
        if value not in named:
            raise ValueError(f"background must be 'black', 'white' or an RGB triple, not {value!r}")
        return named[value]
    rgb = tuple(float(v) for v in value)
    if len(rgb) != 3:
        raise ValueError(f"background must have 3 components, not {value!r}")
    return rgb


def detect_format(path: Path) -> str:
    """The first format (in the readers' order) whose marker files are present, else a DataError."""
    for reader in readers_in_order():
        if reader.detect(path):
            return reader.name
    if path.is_file():
        raise DataError(path, "unknown layout: a dataset is a folder (or a format's own metadata file)")
    raise DataError(path, "unknown layout: found none of " + ", ".join(r.marker for r in readers_in_order()))


__all__ = ["READERS", "Reader", "ReaderOptions", "detect_format", "format_names", "open_dataset", "register_reader",
           "resolve_format"]
