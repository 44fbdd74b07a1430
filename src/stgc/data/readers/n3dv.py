"""N3DV / DyNeRF / LLFF: poses_bounds.npy with camXX/ frame folders or camXX.mp4 videos."""

from __future__ import annotations

from pathlib import Path

import imageio_ffmpeg
import numpy as np

from ...errors import DataError
from ..cameras import Camera, intrinsics, llff_to_w2c
from ..dataset import SourceScene, VideoFrame
from ..images import image_size
from ._common import IMAGE_EXTS, NUMPY_LOAD_ERRORS, _checked, _npy_points
from .registry import ReaderOptions, register_reader


@register_reader("n3dv", order=40, marker="poses_bounds.npy (N3DV)",
                 detect=lambda path: (path.parent if path.name == "poses_bounds.npy" else path).joinpath(
                     "poses_bounds.npy").is_file(),
                 aliases=("dynerf", "llff", "n3d"))
def read_n3dv(path: Path, options: ReaderOptions) -> SourceScene:
    """poses_bounds.npy (one LLFF row per camera, cameras in sorted name order) + camXX/NNNN.png,
    camXX/images/NNNN.png, camXX/N.png or camXX.mp4. Test view: cam00 (the first camera)."""
    root = path.parent if path.is_file() else path
    meta_file = root / "poses_bounds.npy"
    try:
        poses = np.load(meta_file)
    except FileNotFoundError:
        raise DataError(meta_file, "file is missing") from None
    except NUMPY_LOAD_ERRORS as exc:
        raise DataError(meta_file, f"unreadable: {exc}") from None
    if poses.dtype.kind not in "fiu":
        raise DataError(meta_file, f"holds {poses.dtype} values, not real numbers (an [N_cams, 17] float array)")
    if poses.ndim != 2 or poses.shape[1] != 17:
        raise DataError(meta_file, f"expected an [N_cams, 17] array, got shape {poses.shape}")
    frame_dirs = {d.name: d for d in sorted(root.glob("cam*")) if d.is_dir() and _frame_files(d)}
    videos = {v.stem: v for v in sorted(root.glob("cam*.mp4"))}
    names = sorted(frame_dirs) if frame_dirs else sorted(videos)
    if not names:
        raise DataError(root, "no camXX/ frame folders or camXX.mp4 videos next to poses_bounds.npy")
    if len(names) != len(poses):
        what = "cameras without images" if len(poses) > len(names) else "images without a camera pose"
        raise DataError(meta_file, f"{what}: {len(poses)} poses but {len(names)} cameras found ({names[0]}.."
                                   f"{names[-1]})")
    cameras = []
    notes: list[str] = []
    for row, name in zip(poses, names):
        if not np.all(np.isfinite(row)):
            raise DataError(meta_file, f"camera {name}: non-finite (NaN or inf) value in its pose row")
        w2c, (h, w, focal) = llff_to_w2c(row[:15])
        if min(h, w, focal) <= 0:
            raise DataError(meta_file, f"camera {name}: height {h:g}, width {w:g} and focal {focal:g} must be "
                                       "positive")
        if name in frame_dirs:
            files = _frame_files(frame_dirs[name])
            sources: dict[int, Path | VideoFrame] = dict(files)
            actual = image_size(next(iter(files.values())))
        else:
            count, video_fps = _video_frames(videos[name])
            sources = {i: VideoFrame(videos[name], i) for i in range(count)}
            actual = _video_size(videos[name])
        K = intrinsics(focal, focal, w / 2.0, h / 2.0)
        width, height = actual
        if (width, height) != (int(round(w)), int(round(h))):
            # LLFF habit: images stored smaller than the H, W in poses_bounds; accept a uniform factor only.
            sx, sy = width / w, height / h
            if abs(sx - sy) * max(w, h) > 1.0:
                raise DataError(_first_source(sources), f"image is {width}x{height} but poses_bounds.npy says "
                                                        f"{int(w)}x{int(h)} (not a uniform rescale)")
            K[0] *= sx
            K[1] *= sy
            if not notes:
                notes.append(f"images are {width}x{height}; poses_bounds says {int(w)}x{int(h)}: K rescaled")
        _checked(meta_file, name, 0, K, w2c)
        for frame, source in sorted(sources.items()):
            cameras.append(Camera(name, frame, 0.0, K, w2c, width, height, source))
    fps = _video_frames(videos[names[0]])[1] if (not frame_dirs and videos) else None
    points_dir = root / "points3d"
    points, description = None, None
    if points_dir.is_dir() and any(points_dir.glob("*.npy")):
        points = lambda frame: _npy_points(points_dir, frame)
        description = "points3d/NNNN.npy (x, y, z, r, g, b) per frame"
    return SourceScene(name=root.name, format="n3dv", root=root, cameras=cameras, default_test=[names[0]],
                       meta_file=meta_file, fps=fps, points=points, points_description=description, notes=notes,
                       official_config="n3dv")


def _first_source(sources: dict[int, Path | VideoFrame]) -> Path:
    first = sources[min(sources)]
    return first.path if isinstance(first, VideoFrame) else first


def _frame_files(view_dir: Path) -> dict[int, Path]:
    """frame index -> image file in camXX/ or camXX/images/ (names NNNN.png or N.png)."""
    folder = view_dir / "images" if (view_dir / "images").is_dir() else view_dir
    files: dict[int, Path] = {}
    for f in sorted(folder.iterdir()):
        if f.suffix in IMAGE_EXTS and f.stem.isdigit():
            frame = int(f.stem)
            if frame in files:
                raise DataError(f, f"two images for frame {frame} ({files[frame].name} and {f.name})")
            files[frame] = f
    return files


def _video_frames(path: Path) -> tuple[int, float]:
    try:
        count, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
        reader = imageio_ffmpeg.read_frames(str(path))
        meta = next(reader)
        reader.close()
    except (OSError, RuntimeError, StopIteration) as exc:
        raise DataError(path, f"cannot read video: {exc}") from None
    return int(count), float(meta.get("fps") or 30.0)


def _video_size(path: Path) -> tuple[int, int]:
    try:
        reader = imageio_ffmpeg.read_frames(str(path))
        meta = next(reader)
        reader.close()
    except (OSError, RuntimeError, StopIteration) as exc:
        raise DataError(path, f"cannot read video: {exc}") from None
    width, height = (int(v) for v in meta["size"])
    return width, height
