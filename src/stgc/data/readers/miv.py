"""MPEG immersive video (MIV/TMIV): a sequence JSON with `cameras` and one planar YUV 4:2:0 file per view."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ...errors import DataError
from ..cameras import Camera, intrinsics, omaf_to_w2c
from ..dataset import SourceScene, YuvFrame
from ..yuv import count_frames, detect_bit_depth
from ._common import _checked, _fps, _json_type, _load_json
from .registry import ReaderOptions, register_reader

_MIV_TEST_VIEWS = ("v06", "v08")  # the paper's held-out views of the MIV Mirror sequence


def _is_miv_json(path: Path) -> bool:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    cams = data.get("cameras") if isinstance(data, dict) else None
    return isinstance(cams, list) and bool(cams) and isinstance(cams[0], dict) and "Name" in cams[0]


def _is_miv(path: Path) -> bool:
    if path.is_file():
        return path.suffix == ".json" and _is_miv_json(path)
    return any(_is_miv_json(p) for p in sorted(path.glob("*.json")))


@register_reader("miv", order=60, marker="an MIV sequence JSON with 'cameras' (MPEG)", detect=_is_miv,
                 aliases=("mpeg", "tmiv"))
def read_miv(path: Path, options: ReaderOptions) -> SourceScene:
    """MPEG immersive video sequence: a JSON with `cameras` (Name, Position, Rotation [yaw, pitch, roll]
    degrees in OMAF axes, Projection "Perspective", Focal, Principle_point, Resolution) and one planar
    YUV 4:2:0 texture file per view, named '<Name>_texture_<W>x<H>_yuv420p10le.yuv' or '<Name>.yuv'."""
    yuv_range = options.yuv_range

    if path.is_file():
        json_file, root = path, path.parent
    else:
        candidates = [p for p in sorted(path.glob("*.json")) if _is_miv_json(p)]
        if len(candidates) != 1:
            raise DataError(path, f"expected one MIV sequence JSON, found {len(candidates)}")
        json_file, root = candidates[0], path
    meta = _load_json(json_file)
    if not _is_miv_json(json_file):
        raise DataError(json_file, "not an MIV sequence JSON (needs a 'cameras' list of objects with a 'Name')")
    entries = meta["cameras"]
    for k, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise DataError(json_file, f"cameras[{k}] is a {_json_type(entry)}, not an object with Name, Position, "
                                       "Rotation, Focal, Principle_point and Resolution")
    source_names = meta.get("sourceCameraNames")
    if source_names:
        if not isinstance(source_names, list) or not all(isinstance(n, str) for n in source_names):
            raise DataError(json_file, f"sourceCameraNames {source_names!r} is not a list of camera names")
        listed = {str(e.get("Name")) for e in entries}
        unknown = [n for n in source_names if n not in listed]
        if unknown:
            raise DataError(json_file, f"sourceCameraNames lists {', '.join(unknown)}, which no camera entry has")
        entries = [e for e in entries if str(e.get("Name")) in source_names]
    declared_frames = _count(json_file, meta, "Frames_number") or _count(json_file, meta, "numberOfFrames")
    yuv_files = sorted(root.glob("*.yuv"))
    cameras = []
    for entry in entries:
        try:
            name = str(entry["Name"])
            projection = entry.get("Projection", "Perspective")
            position = np.array(entry["Position"], dtype=np.float64)
            rotation = np.array(entry["Rotation"], dtype=np.float64)
            resolution = entry["Resolution"]
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(json_file, f"camera entry without a valid {exc}") from None
        if position.shape != (3,) or rotation.shape != (3,):
            raise DataError(json_file, f"camera {name}: Position and Rotation must be 3 numbers each (x, y, z; yaw, "
                                       f"pitch, roll), not {entry['Position']!r} and {entry['Rotation']!r}")
        try:
            width, height = (int(v) for v in resolution)
        except (TypeError, ValueError):
            width = height = 0
        if width <= 0 or height <= 0:
            raise DataError(json_file, f"camera {name}: Resolution {resolution!r} is not a size (2 positive whole "
                                       "numbers: width, height)")
        if projection != "Perspective":
            raise DataError(json_file, f"camera {name}: projection {projection!r} is not supported (Perspective only)")
        try:
            fx, fy = (float(v) for v in entry["Focal"])
            cx, cy = (float(v) for v in entry["Principle_point"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(json_file, f"camera {name}: missing or bad {exc} (need Focal, Principle_point)") from None
        if not (np.all(np.isfinite(position)) and np.all(np.isfinite(rotation))):
            raise DataError(json_file, f"camera {name}: non-finite (NaN or inf) Position or Rotation")
        K = intrinsics(fx, fy, cx, cy)
        w2c = omaf_to_w2c(position, rotation)
        _checked(json_file, name, 0, K, w2c)
        texture = _miv_texture(name, yuv_files)
        if texture is None:
            raise DataError(json_file, f"camera {name} has no YUV file ('{name}_texture_*.yuv' or '{name}.yuv') "
                                       f"in {root} (cameras without images)")
        if texture.stat().st_size == 0:  # (an interrupted copy) its view vanished, and the default test view moved
            raise DataError(texture, f"holds no frames (an empty file; camera {name} of {json_file.name})")
        bit_depth = detect_bit_depth(texture, width, height, _bit_depth(json_file, name, entry), declared_frames)
        count = count_frames(texture, width, height, bit_depth)
        for i in range(count):
            cameras.append(Camera(name, i, 0.0, K, w2c, width, height,
                                  YuvFrame(texture, i, width, height, bit_depth, yuv_range)))
    names = [c.name for c in cameras]
    test = [n for n in _MIV_TEST_VIEWS if n in names]
    if not test and names:
        test = [names[0]]
    fps = _fps(json_file, meta["Fps"], "Fps") if meta.get("Fps") is not None else _fps(json_file, meta.get("fps"))
    name = str(meta.get("Content_name") or json_file.stem)
    return SourceScene(name=name, format="miv", root=root, cameras=cameras, default_test=test, meta_file=json_file,
                       fps=fps, notes=[f"YUV {yuv_range} range, BT.709"])


def _bit_depth(json_file: Path, name: str, entry: dict[str, Any]) -> int | None:
    """A camera's declared BitDepthColor (None where absent): a whole number of bits from 8 to 16."""
    value = entry.get("BitDepthColor")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not float(value).is_integer() \
            or not 8 <= value <= 16:
        raise DataError(json_file, f"camera {name}: BitDepthColor {value!r} is not a bit depth (a whole number "
                                   "from 8 to 16)")
    return int(value)


def _count(json_file: Path, meta: dict[str, Any], key: str) -> int | None:
    """The sequence's declared number of frames under `key` (None where absent), a positive whole number."""
    value = meta.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise DataError(json_file, f"{key} {value!r} is not a positive whole number of frames")
    return value


def _miv_texture(name: str, files: list[Path]) -> Path | None:
    matches = [f for f in files if f.stem == name or f.stem.startswith(name + "_")]
    matches = [f for f in matches if not any(k in f.stem.lower() for k in ("depth", "geometry", "entity"))]
    textures = [f for f in matches if "texture" in f.stem.lower()] or matches
    return textures[0] if textures else None
