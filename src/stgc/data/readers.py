"""Readers for multi-view video layouts; each returns a `SourceScene` that `assemble` turns into a `Dataset`.

Pixel conventions of the intrinsics (ours: top-left pixel centre at (0.5, 0.5)):
- Panoptic / Dynamic3DGaussians: OpenCV convention (centre at (0, 0)) -> cx + 0.5, cy + 0.5.
- Blender / D-NeRF: cx = W/2 is the image centre in our convention already -> unchanged.
- N3DV / LLFF: only a focal length; principal point at the image centre (W/2, H/2).
- COLMAP (STG preprocessed) and Technicolor (fed to COLMAP unchanged by STG): COLMAP's convention = ours.
- MPEG immersive video: Principle_point is taken as given (image centre = W/2 for a centred camera).
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import DataError
from .cameras import (
    Camera,
    check_pose,
    colmap_intrinsics,
    colmap_to_w2c,
    fov_to_focal,
    intrinsics,
    llff_to_w2c,
    omaf_to_w2c,
    opencv_to_corner_K,
    opengl_c2w_to_w2c,
)
from .dataset import (
    DEFAULT_CACHE_BYTES,
    Dataset,
    SourceScene,
    VideoFrame,
    YuvFrame,
    assemble,
)
from .images import image_size

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
FORMATS = ("panoptic", "blender", "n3dv", "stg-colmap", "technicolor", "miv")
FORMAT_ALIASES = {
    "d3dgs": "panoptic", "dynamic3dgaussians": "panoptic", "panopticsports": "panoptic",
    "dnerf": "blender", "d-nerf": "blender", "nerf": "blender",
    "dynerf": "n3dv", "llff": "n3dv", "n3d": "n3dv",
    "colmap": "stg-colmap", "stg": "stg-colmap",
    "mpeg": "miv", "tmiv": "miv",
}
_MIV_TEST_VIEWS = ("v06", "v08")  # the paper's held-out views of the MIV Mirror sequence


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
    fmt = detect_format(path) if format == "auto" else FORMAT_ALIASES.get(format.lower(), format.lower())
    if fmt not in FORMATS:
        raise DataError(path, f"unknown format {format!r}; choose one of {', '.join(FORMATS)} or 'auto'")
    reader = {
        "panoptic": read_panoptic,
        "blender": read_blender,
        "n3dv": read_n3dv,
        "stg-colmap": read_stg_colmap,
        "technicolor": read_technicolor,
        "miv": lambda p: read_miv(p, yuv_range=yuv_range),
    }[fmt]
    scene = reader(path)
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
    """The format whose marker files are present (the 4DGaussians habit), else a DataError."""
    if path.is_file():
        if path.suffix == ".json" and _is_miv_json(path):
            return "miv"
        if path.name in ("train_meta.json", "test_meta.json"):
            return "panoptic"
        if path.name.startswith("transforms_"):
            return "blender"
        raise DataError(path, "unknown layout: a dataset is a folder (or an MIV sequence .json)")
    if (path / "train_meta.json").is_file():
        return "panoptic"
    if _colmap_frame_dirs(path) or (re.fullmatch(r"colmap_\d+", path.name) and (path / "sparse").is_dir()):
        return "stg-colmap"
    if (path / "transforms_train.json").is_file():
        return "blender"
    if (path / "poses_bounds.npy").is_file():
        return "n3dv"
    if (path / "cameras_parameters.txt").is_file():
        return "technicolor"
    if any(_is_miv_json(p) for p in sorted(path.glob("*.json"))):
        return "miv"
    raise DataError(path, "unknown layout: found none of train_meta.json (Panoptic), colmap_<t>/sparse (STG "
                          "COLMAP), transforms_train.json (Blender/D-NeRF), poses_bounds.npy (N3DV), "
                          "cameras_parameters.txt (Technicolor), or an MIV sequence JSON with 'cameras'")


def _load_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DataError(path, "file is missing") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(path, f"not valid JSON: {exc}") from None


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


# ----------------------------------------------------------------------------------- Panoptic / D3DGS


def read_panoptic(path: Path) -> SourceScene:
    """Dynamic3DGaussians layout: train_meta.json / test_meta.json {w, h, k[t][c], w2c[t][c], fn[t][c],
    cam_id[t][c]} and ims/<fn>. Optional init_pt_cld.npz (static points, used for the first frame)."""
    root = path.parent if path.is_file() else path
    cameras: list[Camera] = []
    test_names: list[str] = []
    meta_files = [root / "train_meta.json", root / "test_meta.json"]
    for meta_file in meta_files:
        if not meta_file.is_file():
            if meta_file.name == "train_meta.json":
                raise DataError(meta_file, "file is missing")
            continue
        meta = _load_json(meta_file)
        try:
            width, height = int(meta["w"]), int(meta["h"])
            ks, w2cs, fns, ids = meta["k"], meta["w2c"], meta["fn"], meta["cam_id"]
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(meta_file, f"missing or bad key {exc} (need w, h, k, w2c, fn, cam_id)") from None
        if not (len(ks) == len(w2cs) == len(fns) == len(ids)):
            raise DataError(meta_file, "k, w2c, fn and cam_id have different numbers of frames")
        for t in range(len(ks)):
            if not (len(ks[t]) == len(w2cs[t]) == len(fns[t]) == len(ids[t])):
                raise DataError(meta_file, f"frame {t}: k, w2c, fn and cam_id have different numbers of cameras")
            for c in range(len(ks[t])):
                name = str(ids[t][c])
                stem = Path(fns[t][c]).stem
                frame = int(stem) if stem.isdigit() else t
                try:
                    K = opencv_to_corner_K(np.array(ks[t][c], dtype=np.float64).reshape(3, 3))
                    w2c = np.array(w2cs[t][c], dtype=np.float64).reshape(4, 4)
                except (ValueError, TypeError):
                    raise DataError(meta_file, f"camera {name} frame {t}: k must be 3x3 and w2c 4x4") from None
                _checked(meta_file, name, frame, K, w2c)
                cameras.append(Camera(name, frame, 0.0, K, w2c, width, height, root / "ims" / fns[t][c]))
                if meta_file.name == "test_meta.json" and name not in test_names:
                    test_names.append(name)
    _check_no_extra_images(root / "ims", {c.image for c in cameras if isinstance(c.image, Path)}, meta_files[0])
    points, description = None, None
    npz = root / "init_pt_cld.npz"
    if npz.is_file():
        first = min(c.frame for c in cameras)
        points = lambda frame: _panoptic_points(npz) if frame == first else None
        description = f"{npz.name} (static cloud, tagged with the first frame)"
    return SourceScene(name=root.name, format="panoptic", root=root, cameras=cameras, default_test=test_names,
                       meta_file=meta_files[0], fps=30.0, points=points, points_description=description,
                       near_plane=PANOPTIC_NEAR_PLANE, masks=_panoptic_masks(root))


# Dynamic 3D Gaussians sets up every Panoptic camera with near = 1.0 (its rasterizer still culls at 0.2; the 1.0
# shapes its depth). The cameras sit on the dome wall, about 3 units from the centre, and nothing of the scene comes
# within 1 unit of a lens, so culling there removes only what the training views cannot place: Gaussians in front
# of one camera that haze a held-out view.
PANOPTIC_NEAR_PLANE = 1.0


def _panoptic_masks(root: Path) -> Callable[[Camera], Path | None] | None:
    """seg/<cam>/<frame>.png beside ims/<cam>/<frame>.jpg (the release ships them for the training cameras)."""
    if not (root / "seg").is_dir():
        return None

    def mask_of(camera: Camera) -> Path | None:
        rel = Path(camera.image).relative_to(root / "ims") if isinstance(camera.image, Path) else None
        if rel is None:
            return None
        path = (root / "seg" / rel).with_suffix(".png")
        return path if path.is_file() else None

    return mask_of


def _panoptic_points(npz: Path) -> tuple[np.ndarray, np.ndarray]:
    data = np.load(npz)["data"]
    return data[:, :3].astype(np.float32), _rgb01(data[:, 3:6])


def _check_no_extra_images(folder: Path, used: set[Path], meta: Path) -> None:
    """Images in camera folders that no camera refers to are an error: the metadata and the images
    disagree, and silently ignoring part of the data hides it."""
    if not folder.is_dir():
        raise DataError(folder, "image folder is missing")
    used_dirs = {p.parent for p in used}
    for d in sorted(used_dirs):
        for f in sorted(d.iterdir()):
            if f.suffix in IMAGE_EXTS and f not in used:
                raise DataError(f, f"extra image: no camera in {meta.name} refers to it")


# ----------------------------------------------------------------------------------- Blender / D-NeRF


def read_blender(path: Path) -> SourceScene:
    """transforms_{train,test}.json with per-frame `time` and c2w in OpenGL axes. Frames with a
    `camera` key are grouped into views (multi-view); otherwise every image is its own view
    (monocular D-NeRF) and frame indices are the ranks of the distinct times."""
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
        entries += [(split, f, meta, fr) for fr in frames]
    multiview = all("camera" in e[3] for e in entries)
    all_times = sorted({float(e[3].get("time", 0.0)) for e in entries})
    cameras, test_names = [], []
    for split, f, meta, fr in entries:
        try:
            file_path = root / fr["file_path"]
            c2w = np.array(fr["transform_matrix"], dtype=np.float64).reshape(4, 4)
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f, f"frame entry without a valid {exc} (need file_path, transform_matrix)") from None
        image = _find_image(file_path)
        if image is None:
            raise DataError(file_path, "image file is missing (no file with this name or a known extension)")
        get = lambda key: fr.get(key, meta.get(key))
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
        K = intrinsics(fx, fy, cx, cy)
        time = float(fr.get("time", 0.0))
        if multiview:
            name = str(fr["camera"])
            frame = int(fr["frame_index"]) if "frame_index" in fr else all_times.index(time)
        else:
            name = f"{split}_{Path(fr['file_path']).name}"  # D-NeRF reuses r_000 in train and test
            frame = all_times.index(time)
        if not np.all(np.isfinite(c2w)):
            raise DataError(f, f"camera {name} frame {frame}: non-finite (NaN or inf) value in transform_matrix")
        w2c = opengl_c2w_to_w2c(c2w)
        _checked(f, name, frame, K, w2c)
        cameras.append(Camera(name, frame, 0.0, K, w2c, width, height, image))
        if split == "test" and name not in test_names:
            test_names.append(name)
    if multiview:
        _check_duplicates(cameras, meta_file)
    fps = first_meta.get("fps")
    points_dir = root / "points3d"
    points, description = None, None
    if points_dir.is_dir() and any(points_dir.glob("*.npy")):
        points = lambda frame: _npy_points(points_dir, frame)
        description = "points3d/NNNN.npy (x, y, z, r, g, b) per frame"
    notes = [] if multiview else ["monocular: each image is its own view"]
    return SourceScene(name=root.name, format="blender", root=root, cameras=cameras, default_test=test_names,
                       meta_file=meta_file, fps=float(fps) if fps else None, multiview=multiview, points=points,
                       points_description=description, notes=notes, synthetic=True)


def _check_duplicates(cameras: list[Camera], meta: Path) -> None:
    seen = set()
    for c in cameras:
        if (c.name, c.frame) in seen:
            raise DataError(meta, f"camera {c.name} frame {c.frame} appears twice")
        seen.add((c.name, c.frame))


def _rgb01(rgb: np.ndarray) -> np.ndarray:
    """Colours as float32 in [0, 1], whether stored as [0, 1] floats or 0..255 values."""
    rgb = np.asarray(rgb, dtype=np.float32)
    if rgb.size and rgb.max() > 1.0 + 1e-6:
        rgb = rgb / 255.0
    return np.clip(rgb, 0.0, 1.0)


def _npy_points(folder: Path, frame: int) -> tuple[np.ndarray, np.ndarray] | None:
    for name in (f"{frame:04d}.npy", f"{frame:06d}.npy", f"{frame}.npy"):
        f = folder / name
        if f.is_file():
            try:
                data = np.load(f)
            except (ValueError, OSError) as exc:
                raise DataError(f, f"unreadable point file: {exc}") from None
            if data.ndim != 2 or data.shape[1] < 6:
                raise DataError(f, f"expected an [M, 6] array (x, y, z, r, g, b), got shape {data.shape}")
            if not np.all(np.isfinite(data[:, :6])):
                raise DataError(f, "non-finite (NaN or inf) point coordinates or colours")
            return data[:, :3].astype(np.float32), _rgb01(data[:, 3:6])
    return None


# ----------------------------------------------------------------------------------- N3DV / LLFF


def read_n3dv(path: Path) -> SourceScene:
    """poses_bounds.npy (one LLFF row per camera, cameras in sorted name order) + camXX/NNNN.png,
    camXX/images/NNNN.png, camXX/N.png or camXX.mp4. Test view: cam00 (the first camera)."""
    root = path.parent if path.is_file() else path
    meta_file = root / "poses_bounds.npy"
    try:
        poses = np.load(meta_file)
    except FileNotFoundError:
        raise DataError(meta_file, "file is missing") from None
    except (ValueError, OSError) as exc:
        raise DataError(meta_file, f"unreadable: {exc}") from None
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
                       meta_file=meta_file, fps=fps, points=points, points_description=description, notes=notes)


def _first_source(sources: dict) -> Path:
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
    import imageio_ffmpeg

    try:
        count, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
        reader = imageio_ffmpeg.read_frames(str(path))
        meta = next(reader)
        reader.close()
    except (OSError, RuntimeError, StopIteration) as exc:
        raise DataError(path, f"cannot read video: {exc}") from None
    return int(count), float(meta.get("fps") or 30.0)


def _video_size(path: Path) -> tuple[int, int]:
    import imageio_ffmpeg

    try:
        reader = imageio_ffmpeg.read_frames(str(path))
        meta = next(reader)
        reader.close()
    except (OSError, RuntimeError, StopIteration) as exc:
        raise DataError(path, f"cannot read video: {exc}") from None
    width, height = (int(v) for v in meta["size"])
    return width, height


# ----------------------------------------------------------------------------------- STG COLMAP


def _colmap_frame_dirs(root: Path) -> dict[int, Path]:
    out = {}
    for d in root.glob("colmap_*"):
        m = re.fullmatch(r"colmap_(\d+)", d.name)
        if m and d.is_dir() and (d / "images").is_dir():
            out[int(m.group(1))] = d
    return dict(sorted(out.items()))


def read_stg_colmap(path: Path) -> SourceScene:
    """Official STG preprocessed layout: colmap_<t>/images/camXX.png + colmap_<t>/sparse/0 per frame.
    Cameras come from the first frame's model (STG reads them from colmap_<start> the same way);
    each frame's points3D is that frame's initial cloud. `path` may be the scene or one colmap_<t>."""
    from .colmap_io import find_model_files, read_model

    default_start = None
    root = path
    m = re.fullmatch(r"colmap_(\d+)", path.name)
    if m:
        root, default_start = path.parent, int(m.group(1))
    dirs = _colmap_frame_dirs(root)
    if not dirs:
        raise DataError(root, "no colmap_<t>/images folders")
    first = default_start if default_start in dirs else min(dirs)
    model_dir = dirs[first] / "sparse" / "0"
    if find_model_files(model_dir) is None:
        raise DataError(model_dir, "no COLMAP model (cameras and images .bin or .txt)")
    model = read_model(model_dir, points=False)
    meta_file = model_dir / ("cameras.bin" if (model_dir / "cameras.bin").is_file() else "cameras.txt")
    views = []
    for im in sorted(model.images.values(), key=lambda im: im.name):
        if im.camera_id not in model.cameras:
            raise DataError(model_dir, f"image {im.name} refers to missing camera {im.camera_id}")
        cam = model.cameras[im.camera_id]
        K, distorted = colmap_intrinsics(cam.model, cam.params)
        if distorted:
            raise DataError(meta_file, f"camera {cam.camera_id} ({cam.model}) has lens distortion: undistort the "
                                       "images first (COLMAP image_undistorter), as STG does")
        w2c = colmap_to_w2c(im.qvec, im.tvec)
        name = Path(im.name).stem
        _checked(model_dir, name, first, K, w2c)
        views.append((name, im.name, K, w2c, cam.width, cam.height))
    if not views:
        raise DataError(model_dir, "the COLMAP model has no images")
    cameras = []
    known = {v[1] for v in views}
    for frame, d in dirs.items():
        for f in sorted((d / "images").iterdir()):
            if f.suffix in IMAGE_EXTS and f.name not in known:
                raise DataError(f, f"extra image: not in the COLMAP model of {model_dir}")
        for name, file_name, K, w2c, width, height in views:
            image = d / "images" / file_name
            if not image.is_file():
                raise DataError(image, f"image file is missing (camera {name}, frame {frame})")
            cameras.append(Camera(name, frame, 0.0, K, w2c, width, height, image))
    names = [v[0] for v in views]
    test = ["cam00"] if "cam00" in names else [sorted(names)[0]]
    points = lambda frame: _colmap_points(dirs.get(frame))
    return SourceScene(name=root.name, format="stg-colmap", root=root, cameras=cameras, default_test=test,
                       meta_file=meta_file, fps=30.0, points=points,
                       points_description="colmap_<t>/sparse/0/points3D per frame", default_start=default_start)


def _colmap_points(frame_dir: Path | None) -> tuple[np.ndarray, np.ndarray] | None:
    from .colmap_io import find_model_files, read_points

    if frame_dir is None:
        return None
    model_dir = frame_dir / "sparse" / "0"
    ext = find_model_files(model_dir)
    if ext is None or not (model_dir / f"points3D.{ext}").is_file():
        return None
    xyz, rgb, _, _ = read_points(model_dir)
    return xyz.astype(np.float32), rgb.astype(np.float32) / 255.0


# ----------------------------------------------------------------------------------- Technicolor


def read_technicolor(path: Path) -> SourceScene:
    """cameras_parameters.txt (a header line, then per camera: f cx cy _ _ qw qx qy qz tx ty tz, a COLMAP-
    style w2c; camera k is row k) + <Scene>_undist_<frame:05d>_<cam:02d>.png. Test view: cam10."""
    root = path.parent if path.is_file() else path
    meta_file = root / "cameras_parameters.txt"
    rows = []
    try:
        lines = meta_file.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise DataError(meta_file, "file is missing") from None
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
            raise DataError(meta_file, f"camera {name} (row {idx + 2}) has no images (cameras without images)")
        files = by_cam[idx]
        width, height = image_size(files[min(files)])
        K = intrinsics(row[0], row[0], row[1], row[2])
        w2c = colmap_to_w2c(np.array(row[5:9]), np.array(row[9:12]))
        _checked(meta_file, name, 0, K, w2c)
        for frame, f in sorted(files.items()):
            cameras.append(Camera(name, frame, 0.0, K, w2c, width, height, f))
    names = [f"cam{i:02d}" for i in range(len(rows))]
    return SourceScene(name=root.name, format="technicolor", root=root, cameras=cameras,
                       default_test=["cam10"] if "cam10" in names else [names[0]], meta_file=meta_file, fps=30.0)


# ----------------------------------------------------------------------------------- MPEG immersive video


def _is_miv_json(path: Path) -> bool:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    cams = data.get("cameras") if isinstance(data, dict) else None
    return isinstance(cams, list) and bool(cams) and isinstance(cams[0], dict) and "Name" in cams[0]


def read_miv(path: Path, yuv_range: str = "limited") -> SourceScene:
    """MPEG immersive video sequence: a JSON with `cameras` (Name, Position, Rotation [yaw, pitch, roll]
    degrees in OMAF axes, Projection "Perspective", Focal, Principle_point, Resolution) and one planar
    YUV 4:2:0 texture file per view, named '<Name>_texture_<W>x<H>_yuv420p10le.yuv' or '<Name>.yuv'."""
    from .yuv import count_frames, detect_bit_depth

    if path.is_file():
        json_file, root = path, path.parent
    else:
        candidates = [p for p in sorted(path.glob("*.json")) if _is_miv_json(p)]
        if len(candidates) != 1:
            raise DataError(path, f"expected one MIV sequence JSON, found {len(candidates)}")
        json_file, root = candidates[0], path
    meta = _load_json(json_file)
    entries = meta["cameras"]
    source_names = meta.get("sourceCameraNames")
    if source_names:
        entries = [e for e in entries if e.get("Name") in source_names]
    declared_frames = meta.get("Frames_number") or meta.get("numberOfFrames")
    yuv_files = sorted(root.glob("*.yuv"))
    cameras = []
    for entry in entries:
        try:
            name = str(entry["Name"])
            projection = entry.get("Projection", "Perspective")
            position = np.array(entry["Position"], dtype=np.float64)
            rotation = np.array(entry["Rotation"], dtype=np.float64)
            width, height = (int(v) for v in entry["Resolution"])
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(json_file, f"camera entry without a valid {exc}") from None
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
        bit_depth = detect_bit_depth(texture, width, height, entry.get("BitDepthColor"), declared_frames)
        count = count_frames(texture, width, height, bit_depth)
        for i in range(count):
            cameras.append(Camera(name, i, 0.0, K, w2c, width, height,
                                  YuvFrame(texture, i, width, height, bit_depth, yuv_range)))
    names = [c.name for c in cameras]
    test = [n for n in _MIV_TEST_VIEWS if n in names]
    if not test and names:
        test = [names[0]]
    fps = meta.get("Fps") or meta.get("fps")
    name = str(meta.get("Content_name") or json_file.stem)
    return SourceScene(name=name, format="miv", root=root, cameras=cameras, default_test=test, meta_file=json_file,
                       fps=float(fps) if fps else None, notes=[f"YUV {yuv_range} range, BT.709"])


def _miv_texture(name: str, files: list[Path]) -> Path | None:
    matches = [f for f in files if f.stem == name or f.stem.startswith(name + "_")]
    matches = [f for f in matches if not any(k in f.stem.lower() for k in ("depth", "geometry", "entity"))]
    textures = [f for f in matches if "texture" in f.stem.lower()] or matches
    return textures[0] if textures else None
