"""A small reader and writer for COLMAP sparse models (cameras, images, points3D; .bin or .txt).

Only what dataset loading needs is kept: cameras, image poses and names, and 3D points with colour,
error and track length. 2D keypoints of images are skipped when reading and written empty, which
COLMAP accepts. Format reference: COLMAP's documentation "Output format" (binary layout is
little-endian: cameras = id i32, model i32, width u64, height u64, params f64[n]; images = id i32,
qvec f64[4], tvec f64[3], camera i32, name NUL-terminated, n2d u64, (x f64, y f64, id i64)[n2d];
points3D = id u64, xyz f64[3], rgb u8[3], error f64, track length u64, (image i32, idx i32)[len]).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DataError
from ..fileio import atomic_open
from .cameras import COLMAP_MODELS

_MODEL_NAMES = {model_id: name for name, (model_id, _) in COLMAP_MODELS.items()}


@dataclass
class ColmapCamera:
    camera_id: int
    model: str
    width: int
    height: int
    params: np.ndarray


@dataclass
class ColmapImage:
    image_id: int
    qvec: np.ndarray  # w, x, y, z (world-to-camera rotation)
    tvec: np.ndarray
    camera_id: int
    name: str


@dataclass
class ColmapModel:
    cameras: dict[int, ColmapCamera] = field(default_factory=dict)
    images: dict[int, ColmapImage] = field(default_factory=dict)
    xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    rgb: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))
    error: np.ndarray = field(default_factory=lambda: np.zeros(0))
    track_length: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def find_model_files(folder: Path) -> str | None:
    """'bin' or 'txt' when `folder` holds a complete COLMAP model in that encoding, else None."""
    for ext in ("bin", "txt"):
        if all((folder / f"{name}.{ext}").is_file() for name in ("cameras", "images")):
            return ext
    return None


def read_model(folder: str | Path, *, points: bool = True) -> ColmapModel:
    """Read a COLMAP sparse model folder (binary preferred when both encodings exist)."""
    folder = Path(folder)
    ext = find_model_files(folder)
    if ext is None:
        raise DataError(folder, "no COLMAP model here (expected cameras and images .bin or .txt)")
    model = ColmapModel()
    try:
        if ext == "bin":
            model.cameras = _read_cameras_bin(folder / "cameras.bin")
            model.images = _read_images_bin(folder / "images.bin")
        else:
            model.cameras = _read_cameras_txt(folder / "cameras.txt")
            model.images = _read_images_txt(folder / "images.txt")
        points_file = folder / f"points3D.{ext}"
        if points and points_file.is_file():
            reader = _read_points_bin if ext == "bin" else _read_points_txt
            model.xyz, model.rgb, model.error, model.track_length = reader(points_file)
    except DataError:
        raise
    except (struct.error, ValueError, IndexError, UnicodeDecodeError) as exc:
        raise DataError(folder, f"corrupt COLMAP {ext} model: {exc}") from None
    return model


def read_points(folder: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(xyz f64 [M,3], rgb u8 [M,3], error f64 [M], track length [M]) of a model folder."""
    model = read_model(folder, points=True)
    return model.xyz, model.rgb, model.error, model.track_length


# ----------------------------------------------------------------------------- binary


class _Reader:
    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def take(self, fmt: str) -> tuple[Any, ...]:
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise DataError(self.path, "file is truncated")
        values = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return values

    def take_array(self, dtype: str | np.dtype, count: int) -> np.ndarray:
        dt = np.dtype(dtype)
        size = dt.itemsize * count
        if self.pos + size > len(self.data):
            raise DataError(self.path, "file is truncated")
        out = np.frombuffer(self.data, dtype=dt, count=count, offset=self.pos)
        self.pos += size
        return out

    def take_cstring(self) -> str:
        end = self.data.find(b"\x00", self.pos)
        if end < 0:
            raise DataError(self.path, "file is truncated (unterminated image name)")
        text = self.data[self.pos : end].decode("utf-8")
        self.pos = end + 1
        return text


def _read_cameras_bin(path: Path) -> dict[int, ColmapCamera]:
    r = _Reader(path)
    cameras = {}
    for _ in range(r.take("<Q")[0]):
        cam_id, model_id, width, height = r.take("<iiQQ")
        if model_id not in _MODEL_NAMES:
            raise DataError(path, f"unknown camera model id {model_id}")
        name = _MODEL_NAMES[model_id]
        params = np.array(r.take_array("<f8", COLMAP_MODELS[name][1]))
        cameras[cam_id] = ColmapCamera(cam_id, name, int(width), int(height), params)
    return cameras


def _read_images_bin(path: Path) -> dict[int, ColmapImage]:
    r = _Reader(path)
    images = {}
    for _ in range(r.take("<Q")[0]):
        image_id, qw, qx, qy, qz, tx, ty, tz, cam_id = r.take("<i7di")
        name = r.take_cstring()
        n2d = r.take("<Q")[0]
        r.take_array("u1", 24 * n2d)  # (x, y, point3D id) rows: not needed
        images[image_id] = ColmapImage(image_id, np.array([qw, qx, qy, qz]), np.array([tx, ty, tz]), cam_id, name)
    return images


_POINT_DTYPE = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"), ("n", "<u8")])


def _read_points_bin(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    r = _Reader(path)
    count = r.take("<Q")[0]
    if count * _POINT_DTYPE.itemsize > len(r.data):  # before allocating for a damaged count
        raise DataError(path, f"says it holds {count} points, more than its {len(r.data)} bytes can")
    xyz = np.zeros((count, 3))
    rgb = np.zeros((count, 3), np.uint8)
    error = np.zeros(count)
    track = np.zeros(count, np.int64)
    for i in range(count):
        row = r.take_array(_POINT_DTYPE, 1)[0]
        xyz[i], rgb[i], error[i], track[i] = row["xyz"], row["rgb"], row["error"], row["n"]
        r.take_array("u1", 8 * int(row["n"]))
    return xyz, rgb, error, track


def write_model(folder: str | Path, model: ColmapModel, ext: str = "bin") -> None:
    """Write `model` as COLMAP `ext` ("bin" or "txt") files into `folder` (atomically per file)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if ext == "bin":
        _write_bin(folder, model)
    elif ext == "txt":
        _write_txt(folder, model)
    else:
        raise ValueError(f"ext must be 'bin' or 'txt', not {ext!r}")


def _write_bin(folder: Path, model: ColmapModel) -> None:
    with atomic_open(folder / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(model.cameras)))
        for cam in model.cameras.values():
            f.write(struct.pack("<iiQQ", cam.camera_id, COLMAP_MODELS[cam.model][0], cam.width, cam.height))
            f.write(np.asarray(cam.params, "<f8").tobytes())
    with atomic_open(folder / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", len(model.images)))
        for im in model.images.values():
            f.write(struct.pack("<i7di", im.image_id, *im.qvec, *im.tvec, im.camera_id))
            f.write(im.name.encode("utf-8") + b"\x00")
            f.write(struct.pack("<Q", 0))
    with atomic_open(folder / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", len(model.xyz)))
        for i in range(len(model.xyz)):
            f.write(struct.pack("<Q3d3Bd", i + 1, *model.xyz[i], *model.rgb[i], float(model.error[i])))
            f.write(struct.pack("<Q", 0))  # empty track: our readers ignore tracks


# ----------------------------------------------------------------------------- text


def _data_lines(path: Path) -> list[tuple[int, str]]:
    lines = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip().startswith("#"):
            lines.append((number, line))
    return lines


def _read_cameras_txt(path: Path) -> dict[int, ColmapCamera]:
    cameras = {}
    for number, line in _data_lines(path):
        parts = line.split()
        if not parts:
            continue
        try:
            cam_id, name, width, height = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
            params = np.array([float(p) for p in parts[4:]])
        except (ValueError, IndexError):
            raise DataError(path, f"line {number}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS") from None
        if name not in COLMAP_MODELS or len(params) != COLMAP_MODELS[name][1]:
            raise DataError(path, f"line {number}: unknown model {name!r} or wrong number of parameters")
        cameras[cam_id] = ColmapCamera(cam_id, name, width, height, params)
    return cameras


def _read_images_txt(path: Path) -> dict[int, ColmapImage]:
    images = {}
    # Records are two lines: the pose line and a (possibly empty) keypoint line. Empty keypoint lines are easy to
    # lose in hand-written files, so a line shaped like a pose line (IMAGE_ID, seven numbers, CAMERA_ID, a name that
    # is not a number) is a pose line even where a keypoint line was due; keypoint lines are all numbers. Where a
    # pose line is due, its name may be a number ("0001").
    expect_pose = True
    for number, line in _data_lines(path):
        parts = line.split()
        if not parts:
            expect_pose = True
            continue
        pose = _image_pose(parts, name_may_be_number=expect_pose)
        if pose is None:
            if expect_pose:
                raise DataError(path, f"line {number}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
            expect_pose = True  # the keypoint line
            continue
        images[pose.image_id] = pose
        expect_pose = False
    return images


def _image_pose(parts: list[str], name_may_be_number: bool = False) -> ColmapImage | None:
    """The image record of a pose line's tokens, or None when they are not one. A numeric name is taken only where
    a pose line is due (`name_may_be_number`), or where the line cannot be keypoints (not whole triples)."""
    if len(parts) < 10:
        return None
    try:
        image_id = int(parts[0])
        values = [float(p) for p in parts[1:8]]
        cam_id = int(parts[8])
    except ValueError:
        return None
    if not name_may_be_number and len(parts) % 3 == 0:
        try:
            float(parts[9])
            return None  # a keypoint line: X Y POINT3D_ID triples, all numbers
        except ValueError:
            pass
    return ColmapImage(image_id, np.array(values[:4]), np.array(values[4:]), cam_id, " ".join(parts[9:]))


def _read_points_txt(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    xyz, rgb, error, track = [], [], [], []
    for number, line in _data_lines(path):
        parts = line.split()
        if not parts:
            continue
        try:
            xyz.append([float(p) for p in parts[1:4]])
            rgb.append([int(p) for p in parts[4:7]])
            error.append(float(parts[7]))
            track.append((len(parts) - 8) // 2)
        except (ValueError, IndexError):
            raise DataError(path, f"line {number}: expected POINT3D_ID X Y Z R G B ERROR TRACK[]") from None
    return (
        np.array(xyz, dtype=np.float64).reshape(-1, 3),
        np.array(rgb, dtype=np.uint8).reshape(-1, 3),
        np.array(error, dtype=np.float64),
        np.array(track, dtype=np.int64),
    )


def _write_txt(folder: Path, model: ColmapModel) -> None:
    with atomic_open(folder / "cameras.txt") as f:
        f.write("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        for cam in model.cameras.values():
            params = " ".join(repr(float(p)) for p in cam.params)
            f.write(f"{cam.camera_id} {cam.model} {cam.width} {cam.height} {params}\n")
    with atomic_open(folder / "images.txt") as f:
        f.write("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n# POINTS2D[] as (X, Y, POINT3D_ID)\n")
        for im in model.images.values():
            pose = " ".join(repr(float(v)) for v in (*im.qvec, *im.tvec))
            f.write(f"{im.image_id} {pose} {im.camera_id} {im.name}\n\n")
    with atomic_open(folder / "points3D.txt") as f:
        f.write("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        for i in range(len(model.xyz)):
            x, y, z = (repr(float(v)) for v in model.xyz[i])
            r, g, b = (int(v) for v in model.rgb[i])
            f.write(f"{i + 1} {x} {y} {z} {r} {g} {b} {float(model.error[i])!r}\n")
