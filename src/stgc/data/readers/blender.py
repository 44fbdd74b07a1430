"""Blender / D-NeRF: transforms_{train,test}.json with per-frame time (multi-view when frames name a camera)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import DataError
from ..cameras import Camera, check_bottom_row, fov_to_focal, intrinsics, opengl_c2w_to_w2c
from ..dataset import SourceScene
from ..images import image_size
from ._common import _checked, _find_image, _fps, _load_json, _npy_points
from .registry import ReaderOptions, register_reader


def _is_blender(path: Path) -> bool:
    if path.is_file():
        return path.name.startswith("transforms_")
    return (path / "transforms_train.json").is_file()


@register_reader("blender", order=30, marker="transforms_train.json (Blender/D-NeRF)", detect=_is_blender,
                 aliases=("dnerf", "d-nerf", "nerf"))
def read_blender(path: Path, options: ReaderOptions) -> SourceScene:
    """transforms_{train,test}.json with per-frame `time` and c2w in OpenGL axes. Frames with a
    `camera` key are grouped into views (multi-view); otherwise every image is its own view
    (monocular D-NeRF) and frame indices are the ranks of the distinct times, placed on the frame axis where their
    times lie (test times fall between training times: `_positions_of_ranks`)."""
    root = path.parent if path.is_file() else path
    splits = {}
    for split in ("train", "test"):
        f = root / f"transforms_{split}.json"
        if f.is_file():
            splits[split] = (f, _load_json(f))
    if "train" not in splits:
        raise DataError(root / "transforms_train.json", "file is missing")
    meta_file, first_meta = splits["train"]
    entries = []  # (split, meta_file, meta, frame_dict)
    for split, (f, meta) in splits.items():
        frames = meta.get("frames")
        if not isinstance(frames, list) or not frames:
            raise DataError(f, "no 'frames' list")
        for k, fr in enumerate(frames):
            if not isinstance(fr, dict):
                raise DataError(f, f"frames[{k}] is {type(fr).__name__}, not an object with file_path and "
                                "transform_matrix")
            entries.append((split, f, meta, fr))
    multiview = all("camera" in e[3] for e in entries)
    if not multiview and any("camera" in e[3] for e in entries):
        # Read as monocular, the entries that name a camera gave "camera ... appears twice", far from the cause.
        split, f, _, fr = next(e for e in entries if "camera" not in e[3])
        raise DataError(f, f"frame {fr.get('file_path')!r} names no camera while other frames do: give every frame "
                        "its 'camera' (multi-view) or none (monocular)")
    all_times = sorted({_time(f, fr) for _, f, _, fr in entries})
    cameras, test_names = [], []
    for split, f, meta, fr in entries:
        try:
            camera = _camera(root, split, f, meta, fr, multiview, all_times)
        except DataError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f, f"frame {fr.get('file_path')!r}: a value cannot be read ({exc})") from None
        cameras.append(camera)
        if split == "test" and camera.name not in test_names:
            test_names.append(camera.name)
    if multiview:  # (a view listed twice for one frame is refused by `assemble`, for every format)
        _check_held_out_whole(entries, splits)
    fps = _fps(meta_file, first_meta.get("fps"))
    points_dir = root / "points3d"
    points, description = None, None
    if points_dir.is_dir() and any(points_dir.glob("*.npy")):
        points = lambda frame: _npy_points(points_dir, frame)
        description = "points3d/NNNN.npy (x, y, z, r, g, b) per frame"
    notes = [] if multiview else ["monocular: each image is its own view"]
    ranked = not multiview or not any("frame_index" in e[3] for e in entries)
    return SourceScene(name=root.name, format="blender", root=root, cameras=cameras, default_test=test_names,
                       meta_file=meta_file, fps=fps, multiview=multiview, points=points,
                       points_description=description, notes=notes, synthetic=True,
                       frame_positions=_positions_of_ranks(all_times) if ranked else None)


def _time(f: Path, fr: dict[str, Any]) -> float:
    """A frame entry's `time` (0 where absent): a finite number, else a DataError naming the file (JSON's Infinity
    and NaN parse as floats, and one of them made every camera's time NaN through the frame positions)."""
    try:
        time = float(fr.get("time", 0.0))
    except (TypeError, ValueError):
        raise DataError(f, f"frame {fr.get('file_path')!r}: time {fr.get('time')!r} is not a number") from None
    if not math.isfinite(time):
        raise DataError(f, f"frame {fr.get('file_path')!r}: time {fr.get('time')!r} is not a finite number")
    return time


def _camera(root: Path, split: str, f: Path, meta: dict[str, Any], fr: dict[str, Any], multiview: bool,
            all_times: list[float]) -> Camera:
    """The camera of one frame entry of transforms_<split>.json (`f`, `meta`)."""
    try:
        file_path = root / fr["file_path"]
        c2w = np.array(fr["transform_matrix"], dtype=np.float64).reshape(4, 4)
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f, f"frame entry without a valid {exc} (need file_path, transform_matrix)") from None
    image = _find_image(file_path)
    if image is None:
        raise DataError(file_path, "image file is missing (no file with this name or a known extension)")

    def get(key: str) -> Any:
        return fr.get(key, meta.get(key))

    width, height = get("w"), get("h")
    if width is None or height is None:
        width, height = image_size(image)
    width, height = int(width), int(height)
    if get("fl_x") is not None:
        fx = float(get("fl_x"))
        fy = float(get("fl_y") if get("fl_y") is not None else fx)
    elif get("camera_angle_x") is not None:
        fx = fov_to_focal(float(get("camera_angle_x")), width)
        fy = fov_to_focal(float(get("camera_angle_y")), height) if get("camera_angle_y") is not None else fx
    else:
        raise DataError(f, "no intrinsics: need fl_x (and cx, cy) or camera_angle_x")
    cx = float(get("cx")) if get("cx") is not None else width / 2.0
    cy = float(get("cy")) if get("cy") is not None else height / 2.0
    _refuse_distortion(f, get)
    K = intrinsics(fx, fy, cx, cy)
    time = _time(f, fr)
    if multiview:
        name = str(fr["camera"])
        frame = int(fr["frame_index"]) if "frame_index" in fr else all_times.index(time)
    else:
        name = f"{split}_{Path(fr['file_path']).name}"  # D-NeRF reuses r_000 in train and test
        frame = all_times.index(time)
    if not np.all(np.isfinite(c2w)):
        raise DataError(f, f"camera {name} frame {frame}: non-finite (NaN or inf) value in transform_matrix")
    # Checked here: the conversion builds a fresh w2c from the top rows, so a c2w written transposed (its translation
    # in the bottom row) would leave every camera at the origin.
    problem = check_bottom_row(c2w, "transform_matrix")
    if problem:
        raise DataError(f, f"camera {name} frame {frame}: {problem}")
    w2c = opengl_c2w_to_w2c(c2w)
    _checked(f, name, frame, K, w2c)
    return Camera(name, frame, 0.0, K, w2c, width, height, image)


def _positions_of_ranks(times: list[float]) -> dict[int, float] | None:
    """Where each rank of the sorted distinct `times` lies on the frame axis: the times mapped linearly so that the
    first is at 0 and the last at len - 1. None when the times are evenly spaced (every rank is its position)."""
    if len(times) < 2:
        return None
    first, last = times[0], times[-1]
    positions = {rank: (t - first) / (last - first) * (len(times) - 1) for rank, t in enumerate(times)}
    if all(abs(position - rank) <= 1e-6 for rank, position in positions.items()):
        return None
    return positions


def _check_held_out_whole(entries: list[tuple[str, Path, Any, Any]], splits: dict[str, tuple[Path, Any]]) -> None:
    """Multi-view scenes hold out whole cameras (every frame of a test camera is a test view): a camera listed in
    both files would have its training images held out with the rest of it, so it is refused."""
    names = {split: {str(fr["camera"]) for s, _, _, fr in entries if s == split} for split in splits}
    both = sorted(names.get("train", set()) & names.get("test", set()))
    if both:
        raise DataError(splits["test"][0], f"camera(s) {', '.join(both)} also in transforms_train.json: a multi-view "
                        "scene holds out whole cameras (all their frames), so list each camera in one file")


# Lens models nerfstudio and instant-ngp write into transforms files; stgc's cameras are pinholes.
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL")


def _refuse_distortion(f: Path, get: Any) -> None:
    """A transforms file of distorted images (nerfstudio's and instant-ngp's k1..k4, p1, p2, a fisheye or
    equirectangular `camera_model`, `is_fisheye`) read as pinhole cameras would train every image off by pixels at
    its edges: refused, as the COLMAP readers refuse such cameras."""
    model = get("camera_model")
    if model is not None and str(model).upper() not in _PINHOLE_MODELS or bool(get("is_fisheye")):
        raise DataError(f, f"camera model {model or 'fisheye'}: only pinhole cameras are supported; undistort "
                           "the images first (e.g. COLMAP's image_undistorter or nerfstudio's processing)")
    try:
        coefficients = {k: float(get(k)) for k in _DISTORTION_KEYS if get(k) is not None}
    except (TypeError, ValueError):
        raise DataError(f, f"a lens distortion coefficient ({', '.join(_DISTORTION_KEYS)}) is not a number") from None
    if any(v != 0.0 for v in coefficients.values()):
        listed = ", ".join(f"{k}={v:g}" for k, v in coefficients.items() if v != 0.0)
        raise DataError(f, f"lens distortion ({listed}) is not modelled: stgc's cameras are pinholes; undistort the "
                           "images first (e.g. COLMAP's image_undistorter or nerfstudio's processing)")
