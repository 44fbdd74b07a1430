"""The official STG preprocessed layout: colmap_<t>/images + colmap_<t>/sparse/0 per frame."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ...errors import DataError
from ..cameras import Camera, colmap_intrinsics, colmap_to_w2c, w2c_center
from ..colmap_io import find_model_files, read_model, read_points
from ..dataset import SourceScene
from ._common import IMAGE_EXTS, _checked
from .registry import ReaderOptions, register_reader


def _colmap_frame_dirs(root: Path) -> dict[int, Path]:
    out = {}
    for d in root.glob("colmap_*"):
        m = re.fullmatch(r"colmap_(\d+)", d.name)
        if m and d.is_dir() and (d / "images").is_dir():
            out[int(m.group(1))] = d
    return dict(sorted(out.items()))


def _is_stg_colmap(path: Path) -> bool:
    if not path.is_dir():
        return False
    return bool(_colmap_frame_dirs(path)) or bool(re.fullmatch(r"colmap_\d+", path.name) and (path / "sparse").is_dir())


@register_reader("stg-colmap", order=20, marker="colmap_<t>/sparse (STG COLMAP)", detect=_is_stg_colmap,
                 aliases=("colmap", "stg"))
def read_stg_colmap(path: Path, options: ReaderOptions) -> SourceScene:
    """Official STG preprocessed layout: colmap_<t>/images/camXX.png + colmap_<t>/sparse/0 per frame.
    Cameras come from the first frame's model (STG reads them from colmap_<start> the same way);
    each frame's points3D is that frame's initial cloud. `path` may be the scene or one colmap_<t>."""
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
    # STG holds out cam00 (Neural 3D Video), but cam10 for Technicolor, whose prepared folder keeps the source's
    # cameras_parameters.txt beside the colmap_<t> folders (STG's readColmapSceneInfoTechnicolor). A prepared
    # Neural 3D Video scene keeps its poses_bounds.npy there (STG's pre_n3d.py writes beside the source).
    technicolor = (root / "cameras_parameters.txt").is_file()
    family = "technicolor" if technicolor else "n3dv" if (root / "poses_bounds.npy").is_file() else None
    held_out = "cam10" if technicolor else "cam00"
    test = [held_out] if held_out in names else [sorted(names)[0]]
    # Without a points3D in any frame the dataset ships no points (init_source=auto then triangulates).
    shipped = any(_points_file(d) is not None for d in dirs.values())
    poses = {file_name: w2c for _, file_name, _, w2c, _, _ in views}
    points = (lambda frame: _colmap_points(dirs.get(frame), model_dir, poses)) if shipped else None
    return SourceScene(name=root.name, format="stg-colmap", root=root, cameras=cameras, default_test=test,
                       meta_file=meta_file, fps=30.0, points=points,
                       points_description="colmap_<t>/sparse/0/points3D per frame", default_start=default_start,
                       official_config=family)


def _points_file(frame_dir: Path) -> Path | None:
    model_dir = frame_dir / "sparse" / "0"
    ext = find_model_files(model_dir)
    return None if ext is None or not (model_dir / f"points3D.{ext}").is_file() else model_dir / f"points3D.{ext}"


def _colmap_points(frame_dir: Path | None, first_model: Path,
                   first_poses: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
    if frame_dir is None or _points_file(frame_dir) is None:
        return None
    model_dir = frame_dir / "sparse" / "0"
    if model_dir != first_model:
        _check_same_world(model_dir, first_model, first_poses)
    xyz, rgb, _, _ = read_points(model_dir)
    if not np.all(np.isfinite(xyz)):
        raise DataError(_points_file(frame_dir), "non-finite (NaN or inf) point coordinates")
    return xyz.astype(np.float32), rgb.astype(np.float32) / 255.0


# Every frame's cameras come from the first frame's model, but each frame's points3D lies in its own model's world
# frame. STG's preparation triangulates every frame from the same known poses, so the models agree to rounding; a
# frame reconstructed on its own (its own SfM run: rotated, shifted, scaled) put its points where no camera looks.
# Poses within this fraction of the cameras' spread (centres) and this many radians (rotations) are the same: a
# looser agreement (a bundle adjustment that moved the poses a little) still lands the points near their place.
_SAME_POSE_TOLERANCE = 1e-2


def _check_same_world(model_dir: Path, first_model: Path, first_poses: dict[str, np.ndarray]) -> None:
    """A DataError naming `model_dir` when its images' poses are not the first frame's (`first_poses`, image name
    -> w2c of `first_model`). Reads only its cameras and images files, once per frame whose points are read."""
    images = read_model(model_dir, points=False).images.values()
    shared = [(im.name, first_poses[im.name], colmap_to_w2c(im.qvec, im.tvec)) for im in images
              if im.name in first_poses]
    if not shared:
        raise DataError(model_dir, f"names none of the images of {first_model}, whose cameras every frame uses: its "
                                   "points cannot be placed in their world frame")
    centres = np.stack([w2c_center(w2c) for w2c in first_poses.values()])
    spread = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max())
    spread = spread if spread > 0 else max(1.0, float(np.linalg.norm(centres[0])))  # one camera: its distance
    for name, first, own in shared:
        moved = float(np.linalg.norm(w2c_center(own) - w2c_center(first))) / spread
        cos = (np.trace(first[:3, :3].T @ own[:3, :3]) - 1.0) / 2.0
        turned = float(np.arccos(np.clip(cos, -1.0, 1.0)))
        if moved > _SAME_POSE_TOLERANCE or turned > _SAME_POSE_TOLERANCE:
            raise DataError(model_dir, f"image {name} has another pose here than in {first_model} (its centre moved "
                                       f"by {moved:.3g} of the cameras' spread, its rotation by "
                                       f"{np.degrees(turned):.3g} degrees): every frame uses the first frame's "
                                       "cameras, so this frame's points would lie in another world frame; "
                                       "triangulate every frame from the same poses (as STG's preparation does)")

