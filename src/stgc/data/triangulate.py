"""Per-frame triangulation of initial points from the images and the known cameras (pycolmap).

Recipe (measured in ../shared/reference/pycolmap_triangulation.md): upsample the images 2x before
SIFT extraction (about 10x more points on 320x180 Panoptic frames at the same error), write the known
intrinsics into the feature database, build a reconstruction with the fixed known poses, match
exhaustively, triangulate, and keep tracks seen by at least 3 images (track-2 points are mostly
mismatches on repetitive texture). pycolmap is optional: importing this module does not need it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from ..errors import DataError, StgcError
from ..fileio import atomic_path
from .cameras import Camera
from .dataset import Dataset
from .readers import open_dataset
from .readers._common import NUMPY_LOAD_ERRORS


TRIANGULATION_SEED = 0  # COLMAP's random generator (RANSAC), fixed so that every run triangulates the same points


@dataclass
class TriangulationResult:
    xyz: np.ndarray  # float32 [M, 3]
    rgb: np.ndarray  # float32 [M, 3] in [0, 1]
    track_length: np.ndarray  # int [M]
    errors: np.ndarray  # reprojection error of every kept observation, original-resolution pixels
    stats: dict[str, Any] = field(default_factory=dict)

    @property
    def median_error(self) -> float:
        return float(np.median(self.errors)) if len(self.errors) else float("nan")


def _pycolmap() -> Any:
    try:
        import pycolmap
    except ImportError:
        raise DataError(None, "triangulation needs pycolmap (pip install 'stgc[colmap]'), or use "
                              "source='random' or points shipped with the data") from None
    pycolmap.logging.minloglevel = 2  # glog chatter on stderr otherwise
    return pycolmap


def cache_dir() -> Path:
    """Where triangulations are kept between runs: $STGC_CACHE_DIR, else $XDG_CACHE_HOME/stgc, else ~/.cache/stgc."""
    if os.environ.get("STGC_CACHE_DIR"):
        return Path(os.environ["STGC_CACHE_DIR"]) / "triangulation"
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "stgc" / "triangulation"


def _cache_key(cameras: list[Camera], upsample: float, min_track_length: int,
               background: tuple[float, float, float]) -> str:
    """Digest of everything the result depends on: cameras, image files (path, size, mtime), how they decode (the
    background RGBA images are composited on, a YUV file's range and depth) and options."""
    two_view = " two-view-tracks" if min_track_length < 3 else ""  # `_triangulate` keeps them then
    h = hashlib.sha256(f"v4 {upsample} {min_track_length} {tuple(background)}{two_view}".encode())
    for cam in cameras:
        h.update(cam.name.encode())
        h.update(np.ascontiguousarray(cam.K).tobytes() + np.ascontiguousarray(cam.w2c).tobytes())
        h.update(f"{cam.width}x{cam.height}".encode())
        source = cam.image
        path = Path(source) if isinstance(source, (str, Path)) else getattr(source, "path", None)
        if path is None:
            return ""  # an in-memory image source: nothing stable to key on
        stat = Path(path).stat()
        decoding = "" if isinstance(source, (str, Path)) else repr(source)  # frozen dataclasses: frame, range, depth
        h.update(f"{Path(path).resolve()} {stat.st_size} {stat.st_mtime_ns} {decoding}".encode())
    return h.hexdigest()[:32]


def triangulate_frame(dataset: Dataset, frame: int, *, views: list[str] | None = None, upsample: float = 2.0,
                      min_track_length: int = 3, include_test: bool = False,
                      use_cache: bool = True) -> TriangulationResult:
    """Triangulate the points of one frame from its training views (or `views`, a subset by name).

    Test views are left out by default so that held-out images never shape the initialisation. Results are
    cached on disk (`cache_dir()`), keyed by the cameras, the image files and the options, because one frame
    costs 5-15 s on 2 cores and a 50-frame segment minutes."""
    cameras = list(dataset.train_at(frame)) + (list(dataset.test_at(frame)) if include_test else [])
    if views is not None:
        cameras = [c for c in cameras if c.name in set(views)]
    if len(cameras) < 2:
        raise DataError(dataset.root, f"frame {frame}: triangulation needs at least 2 views, got {len(cameras)}")
    key = _cache_key(cameras, upsample, min_track_length, dataset.background) if use_cache else ""
    cached = cache_dir() / f"{key}.npz"
    if key and cached.is_file():
        try:
            with np.load(cached, allow_pickle=False) as z:
                return TriangulationResult(z["xyz"], z["rgb"], z["track_length"], z["errors"],
                                           {**json.loads(str(z["stats"])), "cached": True})
        except (*NUMPY_LOAD_ERRORS, KeyError):
            pass  # unreadable cache entry: recompute and overwrite
    result = _triangulate(dataset, frame, cameras, upsample, min_track_length)
    if key:
        try:
            cached.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(cached) as tmp, open(tmp, "wb") as f:
                np.savez(f, xyz=result.xyz, rgb=result.rgb, track_length=result.track_length,
                         errors=result.errors, stats=json.dumps(result.stats))
        except OSError:
            pass  # a read-only home is no reason to fail
    return result


def _triangulate(dataset: Dataset, frame: int, cameras: list[Camera], upsample: float,
                 min_track_length: int) -> TriangulationResult:
    pycolmap = _pycolmap()
    timings = {}
    with tempfile.TemporaryDirectory(prefix="stgc_tri_") as tmp_name:
        tmp = Path(tmp_name)
        image_dir = tmp / "images"
        image_dir.mkdir()
        t0 = time.perf_counter()
        names = {}
        for i, cam in enumerate(cameras):
            file_name = f"{i:03d}_{_safe(cam.name)}.png"
            names[file_name] = cam
            image = Image.fromarray(np.asarray(dataset.load_image(cam)))
            if upsample != 1:
                up = cam.scaled(upsample)
                image = image.resize((up.width, up.height), Image.Resampling.BICUBIC)
            image.save(image_dir / file_name)
        timings["prepare_s"] = time.perf_counter() - t0

        db_path = tmp / "database.db"
        t0 = time.perf_counter()
        # Reproducible: COLMAP's RANSAC draws from a time-seeded generator unless seeded, and its thread pools
        # finish in any order; two runs on one machine triangulated 505 and 504 points (a different initial cloud,
        # a different training). One thread and fixed seeds give the same points on every run.
        pycolmap.set_random_seed(TRIANGULATION_SEED)
        pycolmap.extract_features(
            db_path, image_dir, image_names=sorted(names), camera_mode=pycolmap.CameraMode.PER_IMAGE,
            reader_options=pycolmap.ImageReaderOptions(camera_model="PINHOLE"),
            extraction_options=pycolmap.FeatureExtractionOptions(num_threads=1), device=pycolmap.Device.cpu)
        timings["extract_s"] = time.perf_counter() - t0

        rec = pycolmap.Reconstruction()
        keypoints = 0
        with pycolmap.Database.open(db_path) as db:
            for image in db.read_all_images():
                cam = names[image.name]
                K = cam.scaled(upsample).K  # per axis, the ratio the rounded image size achieved
                db_cam = db.read_camera(image.camera_id)
                db_cam.params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
                db_cam.has_prior_focal_length = True
                db.update_camera(db_cam)
                keypoints += db.num_keypoints_for_image(image.image_id)
                rec.add_camera_with_trivial_rig(pycolmap.Camera(
                    camera_id=image.camera_id, model="PINHOLE", width=db_cam.width, height=db_cam.height,
                    params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]]))
                rec.add_image_with_trivial_frame(
                    pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id),
                    pycolmap.Rigid3d(cam.w2c[:3, :4]))
        t0 = time.perf_counter()
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = TRIANGULATION_SEED
        pycolmap.match_exhaustive(db_path, matching_options=pycolmap.FeatureMatchingOptions(num_threads=1),
                                  verification_options=verification, device=pycolmap.Device.cpu)
        timings["match_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        out_dir = tmp / "sparse"
        out_dir.mkdir()
        options = pycolmap.IncrementalPipelineOptions()
        # COLMAP drops the tracks of two views by default: min_track_length 2 (the only track two views give)
        # found no point.
        options.triangulation.ignore_two_view_tracks = min_track_length > 2
        rec = pycolmap.triangulate_points(rec, db_path, image_dir, out_dir, clear_points=True, options=options,
                                          refine_intrinsics=False)
        timings["triangulate_s"] = time.perf_counter() - t0
        by_id = {image_id: names[img.name] for image_id, img in rec.images.items()}
        xyz, rgb, tracks, errors = [], [], [], []
        total = 0
        for point in rec.points3D.values():
            total += 1
            length = point.track.length()
            if length < min_track_length:
                continue
            xyz.append(point.xyz)
            rgb.append(point.color)
            tracks.append(length)
            for element in point.track.elements:
                cam = by_id[element.image_id]
                up = cam.scaled(upsample)
                observed = (np.asarray(rec.images[element.image_id].points2D[element.point2D_idx].xy)
                            / (up.width / cam.width, up.height / cam.height))
                projected, _ = cam.project(np.asarray(point.xyz)[None])
                errors.append(float(np.linalg.norm(projected[0] - observed)))
    result = TriangulationResult(
        xyz=np.array(xyz, dtype=np.float32).reshape(-1, 3),
        rgb=np.array(rgb, dtype=np.float32).reshape(-1, 3) / 255.0,
        track_length=np.array(tracks, dtype=np.int64),
        errors=np.array(errors),
    )
    result.stats = {
        "frame": frame,
        "views": len(cameras),
        "upsample": upsample,
        "keypoints_per_image": keypoints / len(cameras),
        "points_all_tracks": total,
        "points": len(result.xyz),
        "min_track_length": min_track_length,
        "mean_track_length": float(result.track_length.mean()) if len(result.xyz) else 0.0,
        "median_error_px": result.median_error,
        "mean_error_px": float(result.errors.mean()) if len(result.errors) else float("nan"),
        **{k: round(v, 3) for k, v in timings.items()},
    }
    return result



def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)


def main(argv: list[str] | None = None) -> int:
    """`python -m stgc.data.triangulate DATA`: triangulate every frame of a segment, print a per-frame table
    (or JSON rows with --json). Measures what source='triangulate' gives before a training run."""

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("data", help="dataset path (any supported layout)")
    parser.add_argument("--format", default="auto")
    parser.add_argument("--start", type=int, default=None)
    parser.add_argument("--duration", type=int, default=None)
    parser.add_argument("--views-every", type=int, default=1, help="use every k-th training view")
    parser.add_argument("--upsample", type=float, default=2.0)
    parser.add_argument("--min-track-length", type=int, default=3)
    parser.add_argument("--json", action="store_true", help="one JSON object per frame instead of a table")
    parser.add_argument("--no-cache", action="store_true", help="recompute even when a cached result exists")
    args = parser.parse_args(argv)
    if args.views_every < 1:
        parser.error(f"--views-every {args.views_every}: at least 1")
    try:
        return _print_triangulation(args)
    except StgcError as exc:  # a bad dataset is one line naming the file, as in `stgc`
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2


def _print_triangulation(args: argparse.Namespace) -> int:
    dataset = open_dataset(args.data, format=args.format, start=args.start, duration=args.duration)
    views = dataset.train_views[:: args.views_every]
    columns = ["frame", "views", "keypoints_per_image", "points_all_tracks", "points", "mean_track_length",
               "median_error_px", "mean_error_px", "extract_s", "match_s", "triangulate_s"]
    if not args.json:
        print(" ".join(f"{c:>12s}" for c in columns), flush=True)
    total = 0
    for frame in dataset.frames:
        stats = triangulate_frame(dataset, frame, views=views, upsample=args.upsample,
                                  min_track_length=args.min_track_length, use_cache=not args.no_cache).stats
        total += stats["points"]
        if args.json:
            print(json.dumps(stats), flush=True)
        else:
            print(" ".join(f"{stats[c]:>12.3f}" if isinstance(stats[c], float) else f"{stats[c]:>12}"
                           for c in columns), flush=True)
    if not args.json:
        print(f"total points over {len(dataset.frames)} frames: {total}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
