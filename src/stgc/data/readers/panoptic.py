"""Panoptic / Dynamic 3D Gaussians (PanopticSports): train_meta.json, test_meta.json, ims/, seg/."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ...errors import DataError
from ..cameras import Camera, opencv_to_corner_K
from ..dataset import SourceScene
from ._common import IMAGE_EXTS, NUMPY_LOAD_ERRORS, _checked, _load_json, _rgb01
from .registry import ReaderOptions, register_reader


def _is_panoptic(path: Path) -> bool:
    if path.is_file():
        return path.name in ("train_meta.json", "test_meta.json")
    return (path / "train_meta.json").is_file()


@register_reader("panoptic", order=10, marker="train_meta.json (Panoptic)", detect=_is_panoptic,
                 aliases=("d3dgs", "dynamic3dgaussians", "panopticsports"))
def read_panoptic(path: Path, options: ReaderOptions) -> SourceScene:
    """Dynamic3DGaussians layout: train_meta.json / test_meta.json {w, h, k[t][c], w2c[t][c], fn[t][c],
    cam_id[t][c]} and ims/<fn>. Optional init_pt_cld.npz (static points, used for the first frame of each segment)."""
    root = path.parent if path.is_file() else path
    cameras: list[Camera] = []
    test_names: list[str] = []
    train_names: set[str] = set()
    referred: dict[Path, Path] = {}  # each camera's image -> the metadata file that names it
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
        if not all(isinstance(v, list) for v in (ks, w2cs, fns, ids)):
            raise DataError(meta_file, "k, w2c, fn and cam_id must be lists (one entry per frame)")
        if not (len(ks) == len(w2cs) == len(fns) == len(ids)):
            raise DataError(meta_file, "k, w2c, fn and cam_id have different numbers of frames")
        for t in range(len(ks)):
            if not all(isinstance(v[t], list) for v in (ks, w2cs, fns, ids)):
                raise DataError(meta_file, f"frame {t}: k, w2c, fn and cam_id must be lists (one entry per camera)")
            if not (len(ks[t]) == len(w2cs[t]) == len(fns[t]) == len(ids[t])):
                raise DataError(meta_file, f"frame {t}: k, w2c, fn and cam_id have different numbers of cameras")
            for c in range(len(ks[t])):
                name = str(ids[t][c])
                if not isinstance(fns[t][c], str):
                    raise DataError(meta_file, f"camera {name} frame {t}: fn {fns[t][c]!r} is not a file name")
                stem = Path(fns[t][c]).stem
                frame = int(stem) if stem.isdigit() else t
                try:
                    K = opencv_to_corner_K(np.array(ks[t][c], dtype=np.float64).reshape(3, 3))
                    w2c = np.array(w2cs[t][c], dtype=np.float64).reshape(4, 4)
                except (ValueError, TypeError):
                    raise DataError(meta_file, f"camera {name} frame {t}: k must be 3x3 and w2c 4x4") from None
                _checked(meta_file, name, frame, K, w2c)
                cameras.append(Camera(name, frame, 0.0, K, w2c, width, height, root / "ims" / fns[t][c]))
                referred.setdefault(root / "ims" / fns[t][c], meta_file)
                if meta_file.name == "train_meta.json":
                    train_names.add(name)
                elif name not in test_names:
                    test_names.append(name)
    _check_held_out_whole(train_names, test_names, meta_files[1])
    _check_no_extra_images(root / "ims", referred, meta_files)
    points, description = None, None
    npz = root / "init_pt_cld.npz"
    if npz.is_file():
        points = lambda frame: _panoptic_points(npz)
        description = f"{npz.name} (static cloud, tagged with the segment's first frame)"
    return SourceScene(name=root.name, format="panoptic", root=root, cameras=cameras, default_test=test_names,
                       meta_file=meta_files[0], fps=30.0, points=points, points_description=description,
                       near_plane=PANOPTIC_NEAR_PLANE, view_dependent_colour=False,
                       masks=_panoptic_masks(root), static_points=points is not None)


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
    try:
        with np.load(npz) as archive:
            data = np.asarray(archive["data"], dtype=np.float64)
    except KeyError:
        raise DataError(npz, "no 'data' array (Dynamic 3D Gaussians' [N, 7]: x, y, z, r, g, b, seg)") from None
    except NUMPY_LOAD_ERRORS as exc:
        raise DataError(npz, f"unreadable point cloud: {exc}") from None
    if data.ndim != 2 or data.shape[1] < 6:
        raise DataError(npz, f"'data' is {list(data.shape)}; expected [N, 7] (x, y, z, r, g, b, seg)")
    if not np.all(np.isfinite(data[:, :6])):
        raise DataError(npz, "non-finite (NaN or inf) point coordinates or colours")
    return data[:, :3].astype(np.float32), _rgb01(data[:, 3:6])


def _check_held_out_whole(train_names: set[str], test_names: list[str], test_meta: Path) -> None:
    """The held-out views are whole cameras (every frame of a camera in test_meta.json is a test view): a camera
    also in train_meta.json had its training images held out with it, and its test frames listed twice, so it is
    refused (as the Blender reader refuses one in both transforms files)."""
    both = [name for name in test_names if name in train_names]
    if both:
        raise DataError(test_meta, f"camera(s) {', '.join(both)} also in train_meta.json: the held-out views are "
                        "whole cameras (all their frames), so list each camera in one file")


def _check_no_extra_images(folder: Path, used: dict[Path, Path], metas: list[Path]) -> None:
    """Images that no camera refers to are an error: the metadata and the images disagree, and silently ignoring part
    of the data hides it. That holds for whole camera folders too (ims/<cam>/ with images that neither metadata file
    names): without test_meta.json (skipped when absent) the held-out cameras' folders were dropped without a word.
    `used`: each image a camera refers to, and the metadata file that does."""
    if not folder.is_dir():
        raise DataError(folder, "image folder is missing")
    named: set[str] = set()
    for p in used:
        try:
            parts = p.relative_to(folder).parts
        except ValueError:
            continue
        if len(parts) > 1:
            named.add(parts[0])
    unnamed = sorted((d for d in folder.iterdir() if d.is_dir() and d.name not in named and _holds_images(d)),
                     key=lambda d: (len(d.name), d.name))
    present = [m.name for m in metas if m.is_file()]
    if unnamed:
        test_meta = metas[-1]
        hint = "" if test_meta.is_file() else f"; {test_meta.name} is missing: the held-out cameras' metadata?"
        raise DataError(folder, f"camera folder(s) {', '.join(d.name for d in unnamed)} hold images that no camera "
                                f"in {' or '.join(present)} refers to{hint}")
    used_dirs = {p.parent for p in used}
    for d in sorted(used_dirs):
        if not d.is_dir():  # listing it raised a bare FileNotFoundError (NotADirectoryError for a file there)
            image = min(p for p in used if p.parent == d)
            raise DataError(d, f"camera image folder {'is not a folder' if d.exists() else 'is missing'}: "
                               f"{used[image].name} refers to images in it ({image.name}, ...)")
        for f in sorted(d.iterdir()):
            if f.suffix in IMAGE_EXTS and f not in used:
                raise DataError(f, f"extra image: no camera in {' or '.join(present)} refers to it")


def _holds_images(folder: Path) -> bool:
    return any(f.suffix in IMAGE_EXTS for f in folder.iterdir())
