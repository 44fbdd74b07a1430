"""Helpers shared by the readers."""

from __future__ import annotations

import json
import math
import zipfile
from pathlib import Path
from typing import Any, cast

import numpy as np

from ...errors import DataError
from ..cameras import check_pose

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
# What np.load raises on a damaged file besides OSError/ValueError: EOFError when it is empty, BadZipFile when an
# .npz is truncated.
NUMPY_LOAD_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile)


def _load_json(path: Path) -> dict[str, Any]:
    """The JSON object in `path`; every reader's metadata file is one (a list or a string at the top level was an
    AttributeError from the reader's first `.get`)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DataError(path, "file is missing") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(path, f"not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise DataError(path, f"top level is not a JSON object (it is a {_json_type(data)})")
    return cast(dict[str, Any], data)


def _json_type(value: Any) -> str:
    """The JSON name of a decoded value's type, for messages."""
    for kind, name in ((bool, "boolean"), (dict, "object"), (list, "list"), (str, "string"), (int, "number"),
                       (float, "number")):
        if isinstance(value, kind):
            return name
    return "null" if value is None else type(value).__name__


def _fps(meta_file: Path, value: Any, key: str = "fps") -> float | None:
    """A metadata file's frame rate: None where it states none, else a positive finite number (a number or a
    numeric string), else a DataError naming the file ('30fps' was a ValueError traceback, and a negative or
    infinite rate was accepted until a later step divided by it)."""
    if value is None:
        return None
    try:
        if isinstance(value, bool):
            raise TypeError
        fps = float(value)
    except (TypeError, ValueError):
        fps = math.nan
    if not (math.isfinite(fps) and fps > 0):
        raise DataError(meta_file, f"{key} {value!r} is not a positive number (frames per second)")
    return fps


def _checked(meta: Path, name: str, frame: int, K: np.ndarray, w2c: np.ndarray) -> None:
    problem = check_pose(w2c, K)
    if problem:
        raise DataError(meta, f"camera {name} frame {frame}: {problem}")


def _find_image(base: Path) -> Path | None:
    """`base` itself if it exists, else `base` with a known image extension (D-NeRF omits it)."""
    if base.is_file():
        return base
    for ext in IMAGE_EXTS:
        candidate = base.with_name(base.name + ext)
        if candidate.is_file():
            return candidate
    return None


def _rgb01(rgb: np.ndarray) -> np.ndarray:
    """Colours as float32 in [0, 1], whether stored as [0, 1] values or 0..255 ones (one array holds both the
    coordinates and the colours, so its dtype cannot tell). Above 2 they are 0..255: a [0, 1] colour a renderer left
    slightly over 1 is clipped, not read as a nearly black 0..255 one."""
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.size and rgb.max() > 2.0:
        rgb = rgb / 255.0
    return np.clip(rgb, 0.0, 1.0)


def _npy_points(folder: Path, frame: int) -> tuple[np.ndarray, np.ndarray] | None:
    for name in (f"{frame:04d}.npy", f"{frame:06d}.npy", f"{frame}.npy"):
        f = folder / name
        if f.is_file():
            try:
                data = np.load(f)
            except NUMPY_LOAD_ERRORS as exc:
                raise DataError(f, f"unreadable point file: {exc}") from None
            if data.ndim != 2 or data.shape[1] < 6:
                raise DataError(f, f"expected an [M, 6] array (x, y, z, r, g, b), got shape {data.shape}")
            if not np.all(np.isfinite(data[:, :6])):
                raise DataError(f, "non-finite (NaN or inf) point coordinates or colours")
            return data[:, :3].astype(np.float32), _rgb01(data[:, 3:6])
    return None
