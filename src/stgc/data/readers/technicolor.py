"""Technicolor light-field video as STG's pre_technicolor.py expects it: cameras_parameters.txt + undistorted PNGs."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ...errors import DataError
from ..cameras import Camera, colmap_to_w2c, intrinsics
from ..dataset import SourceScene
from ..images import image_size
from ._common import IMAGE_EXTS, _checked
from .registry import ReaderOptions, register_reader


@register_reader("technicolor", order=50, marker="cameras_parameters.txt (Technicolor)",
                 detect=lambda path: (path.parent if path.name == "cameras_parameters.txt" else path).joinpath(
                     "cameras_parameters.txt").is_file())
def read_technicolor(path: Path, options: ReaderOptions) -> SourceScene:
    """cameras_parameters.txt (a header line, then per camera: f cx cy _ _ qw qx qy qz tx ty tz, a COLMAP-
    style w2c; camera k is row k) + <Scene>_undist_<frame:05d>_<cam:02d>.png. Test view: cam10."""
    root = path.parent if path.is_file() else path
    meta_file = root / "cameras_parameters.txt"
    rows = []
    line_numbers = []  # each row's line in the file (blank lines are skipped)
    try:
        lines = meta_file.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise DataError(meta_file, "file is missing") from None
    except UnicodeDecodeError as exc:
        raise DataError(meta_file, f"not a text file of numbers ({exc.reason} at byte {exc.start})") from None
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in line.split()]
        except ValueError:
            raise DataError(meta_file, f"line {number}: not a row of numbers") from None
        if len(values) < 12:
            raise DataError(meta_file, f"line {number}: expected 12 numbers (f cx cy _ _ qw qx qy qz tx ty tz)")
        rows.append(values)
        line_numbers.append(number)
    pattern = re.compile(r"(.+)_undist_(\d+)_(\d+)$")
    by_cam: dict[int, dict[int, Path]] = {}
    for f in sorted(root.iterdir()):
        m = pattern.match(f.stem)
        if m and f.suffix in IMAGE_EXTS:
            by_cam.setdefault(int(m.group(3)), {})[int(m.group(2))] = f
    if not by_cam:
        raise DataError(root, "no <Scene>_undist_<frame>_<cam>.png images")
    extra = sorted(c for c in by_cam if c >= len(rows))
    if extra:
        raise DataError(by_cam[extra[0]][min(by_cam[extra[0]])], f"images of camera {extra[0]} but "
                                                                 f"{meta_file.name} has only {len(rows)} cameras")
    cameras = []
    for idx, row in enumerate(rows):
        name = f"cam{idx:02d}"
        if idx not in by_cam:
            raise DataError(meta_file, f"camera {name} (line {line_numbers[idx]}) has no images (cameras without "
                                       "images)")
        files = by_cam[idx]
        width, height = image_size(files[min(files)])
        # The file states no image size: resized images under full-size intrinsics would load without a word
        # (K is not scaled to them). A real camera's principal point lies near the middle of its image.
        if not (width / 4 < row[1] < 3 * width / 4 and height / 4 < row[2] < 3 * height / 4):
            raise DataError(meta_file, f"line {line_numbers[idx]} (camera {name}): principal point ({row[1]:g}, "
                                       f"{row[2]:g}) is far from the middle of its {width}x{height} images "
                                       f"({files[min(files)].name}): the parameters are for images of another size "
                                       "(the official scenes' are 2048x1088); scale f, cx and cy with the images")
        K = intrinsics(row[0], row[0], row[1], row[2])
        w2c = colmap_to_w2c(np.array(row[5:9]), np.array(row[9:12]))
        _checked(meta_file, name, 0, K, w2c)
        for frame, f in sorted(files.items()):
            cameras.append(Camera(name, frame, 0.0, K, w2c, width, height, f))
    names = [f"cam{i:02d}" for i in range(len(rows))]
    return SourceScene(name=root.name, format="technicolor", root=root, cameras=cameras,
                       default_test=["cam10"] if "cam10" in names else [names[0]], meta_file=meta_file, fps=30.0,
                       official_config="technicolor")
