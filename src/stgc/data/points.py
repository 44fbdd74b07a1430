"""Initial point clouds, one set of points per frame tagged with the frame's time (STG's initialisation)."""

from __future__ import annotations

import logging
import warnings
import weakref
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from ..errors import DataError
from .dataset import Dataset
from .masks import hull_colours, visual_hull
from .triangulate import triangulate_frame

log = logging.getLogger(__name__)

InitSource = Literal["auto", "data", "triangulate", "random"]
SOURCES = get_args(InitSource)


@dataclass
class PointCloud:
    """Points with colour and time: xyz float32 [M, 3], rgb float32 [M, 3] in [0, 1], time float32 [M]."""

    xyz: np.ndarray
    rgb: np.ndarray
    time: np.ndarray

    def __post_init__(self) -> None:
        self.xyz = np.asarray(self.xyz, dtype=np.float32).reshape(-1, 3)
        self.rgb = np.asarray(self.rgb, dtype=np.float32).reshape(-1, 3)
        self.time = np.asarray(self.time, dtype=np.float32).reshape(-1)
        if not (len(self.xyz) == len(self.rgb) == len(self.time)):
            raise ValueError(f"xyz, rgb and time lengths differ: {len(self.xyz)}, {len(self.rgb)}, {len(self.time)}")

    def __len__(self) -> int:
        return len(self.xyz)

    @staticmethod
    def empty() -> PointCloud:
        return PointCloud(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))

    @staticmethod
    def concatenate(clouds: list[PointCloud]) -> PointCloud:
        if not clouds:
            return PointCloud.empty()
        return PointCloud(np.concatenate([c.xyz for c in clouds]), np.concatenate([c.rgb for c in clouds]),
                          np.concatenate([c.time for c in clouds]))

    def select(self, mask: np.ndarray) -> PointCloud:
        return PointCloud(self.xyz[mask], self.rgb[mask], self.time[mask])

    def counts_per_time(self) -> dict[float, int]:
        values, counts = np.unique(self.time, return_counts=True)
        return {float(v): int(c) for v, c in zip(values, counts)}


def _subsample(xyz: np.ndarray, rgb: np.ndarray, limit: int | None,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    if limit is None or len(xyz) <= limit:
        return xyz, rgb
    keep = np.sort(rng.choice(len(xyz), size=limit, replace=False))
    return xyz[keep], rgb[keep]


def thin_like(cloud: PointCloud, raw: PointCloud, cap: int | None, seed: int = 0) -> PointCloud:
    """Randomly thin each frame of `cloud` (a subset of `raw`) by the factor a per-frame cap of `cap` points would
    apply to that frame of `raw`: round(kept * min(1, cap / raw count)) points stay. None = no cap."""
    if cap is None:
        return cloud
    rng = np.random.default_rng(seed)
    raw_counts = raw.counts_per_time()
    keep = np.zeros(len(cloud), dtype=bool)
    for t in np.unique(cloud.time):
        idx = np.flatnonzero(cloud.time == t)
        factor = min(1.0, cap / raw_counts[float(t)])
        take = min(len(idx), int(round(len(idx) * factor)))
        # Draw only where thinning happens: without a preprocess rule this is the plain cap, same draws as before.
        keep[idx if take == len(idx) else np.sort(rng.choice(idx, size=take, replace=False))] = True
    return cloud.select(keep)


def initial_points(dataset: Dataset, source: str = "auto", frames: list[int] | None = None,
                   max_points_per_frame: int | None = None, seed: int = 0, *, triangulation_upsample: float = 2.0,
                   min_track_length: int = 3, random_points_per_frame: int = 2000,
                   triangulation_cache: bool = True, mask_points_per_frame: int = 0) -> PointCloud:
    """Initial points of the frames `frames` (absolute indices; default: all frames of the segment).

    source: "data" = points shipped with the data (COLMAP points3D, points3d/NNNN.npy, init_pt_cld.npz);
    "triangulate" = SIFT + known-pose triangulation with pycolmap from the training views; "random" =
    uniform points in the region the cameras see (with a warning); "auto" = data if present, else
    triangulation if pycolmap imports and every frame has `min_track_length` training views (a point needs that
    many) or masks give it hull points, else random.

    mask_points_per_frame > 0 adds, where the data has foreground masks, up to that many points per frame inside
    the masks' visual hull (`mask_hull_points`): the moving subjects, which triangulation misses."""
    if source not in SOURCES:
        raise ValueError(f"source must be one of {SOURCES}, not {source!r}")
    frames = list(dataset.frames if frames is None else frames)
    outside = [f for f in frames if f not in dataset.frames]
    if outside:
        raise DataError(dataset.root, f"frames {outside} are not in the segment [{dataset.start}, "
                                      f"{dataset.start + dataset.duration})")
    if not frames:
        raise DataError(dataset.root, "empty frame list for initial points")
    if source == "auto":
        if dataset.has_points:
            source = "data"
        elif any(len(dataset.train_at(f)) < 2 for f in frames):
            # Monocular data: one view per frame, nothing to triangulate.
            log.info("%s: fewer than 2 training views in some frame; random initial points", dataset.name)
            source = "random"
        elif (any(len(dataset.train_at(f)) < min_track_length for f in frames)
              and not (mask_points_per_frame > 0 and dataset.has_masks)):
            # Too few views for a track of min_track_length: triangulation would find nothing, and no visual hull
            # fills the frame in (with one, triangulation stays: the hull's points were the frame's).
            log.info("%s: fewer than %d training views (min_track_length) in some frame; random initial points",
                     dataset.name, min_track_length)
            source = "random"
        else:
            try:
                import pycolmap  # noqa: F401

                source = "triangulate"
            except ImportError:
                source = "random"
    if source in ("triangulate", "random"):  # (auto resolved first: monocular data's test-only frames too)
        unseen = [f for f in frames if not dataset.train_at(f)]
        if unseen:
            raise DataError(dataset.root, f"frames {unseen} have no training camera: {source} points need one "
                                          f"(Dataset.train_frames lists the frames that have)")
    rng = np.random.default_rng(seed)
    hull = mask_points_per_frame > 0 and dataset.has_masks
    if hull:
        unmasked = [c.name for c in dataset.train_at(frames[0]) if dataset.mask_path(c) is None]
        if unmasked:  # said once here, not per frame
            log.warning("%s: training views %s have no foreground mask; the visual hull uses the others",
                        dataset.name, ", ".join(unmasked))
    clouds = []
    without: list[int] = []  # frames of per-frame shipped points that have none (a missing or empty file)
    for frame in frames:
        t = dataset.time_of(frame)
        if source == "data":
            if not dataset.has_points:
                raise DataError(dataset.root, "no initial points ship with this dataset (use source='triangulate' "
                                              "or 'random')")
            # None: e.g. a static cloud given for the first frame only; the frame still gets its hull points.
            got = dataset.data_points(frame)
            xyz, rgb = got if got is not None else (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
            if len(xyz) == 0 and dataset.ships_points_for(frame):
                without.append(frame)
        elif source == "triangulate":

            result = triangulate_frame(dataset, frame, upsample=triangulation_upsample,
                                       min_track_length=min_track_length, use_cache=triangulation_cache)
            log.info("frame %d: %d triangulated points, median reprojection error %.3f px", frame,
                     len(result.xyz), result.median_error)
            xyz, rgb = result.xyz, result.rgb
        else:
            count = max_points_per_frame or random_points_per_frame
            xyz, rgb = random_points(dataset, frame, count, rng)
        xyz, rgb = np.asarray(xyz), np.asarray(rgb)
        if hull:
            hull_xyz, hull_rgb = mask_hull_points(dataset, frame, mask_points_per_frame, rng)
            log.info("frame %d: %d points inside the masks' visual hull", frame, len(hull_xyz))
            xyz, rgb = np.concatenate([xyz, hull_xyz]), np.concatenate([rgb, hull_rgb])
        xyz, rgb = _subsample(xyz, rgb, max_points_per_frame, rng)  # the frame's cap covers its hull points
        clouds.append(PointCloud(xyz, rgb, np.full(len(xyz), t)))
    if without and len(without) < len(frames):
        log.warning("%s: frames %s ship no points (%s); they start without initial points of their own",
                    dataset.name, _frame_list(without), dataset.points_description or "the data's points")
    cloud = PointCloud.concatenate(clouds)
    if len(cloud) == 0:
        raise DataError(dataset.root, f"no initial points found for frames {frames} with source {source!r}")
    return cloud


# The datasets whose empty masks were reported (`mask_hull_points` says so once per dataset, not once per frame).
_SAID_EMPTY_MASKS: weakref.WeakSet[Dataset] = weakref.WeakSet()


def mask_hull_points(dataset: Dataset, frame: int, count: int, rng: np.random.Generator,
                     resolution: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """Up to `count` voxel centres of the visual hull of the training views' masks at `frame` (a cube of side twice
    the viewing radius around the viewing region, `resolution` voxels a side), coloured from the foreground pixels
    they project to; each jittered uniformly within its voxel. Views without a mask are left out."""
    cameras, masks = [], []
    for cam in dataset.train_at(frame):
        mask = dataset.load_mask(cam)
        if mask is not None:
            cameras.append(cam)
            masks.append(mask)
    if masks and not any(mask.any() for mask in masks) and dataset not in _SAID_EMPTY_MASKS:
        _SAID_EMPTY_MASKS.add(dataset)
        log.warning("%s: every training view's foreground mask at frame %d is empty (all background, e.g. %s): the "
                    "visual hull adds no points there. Masks are read as 0/255 or 0/1 greyscale, 1-bit, or palette "
                    "images (index 0 background); said once", dataset.name, frame, dataset.mask_path(cameras[0]))
    if len(cameras) < 2:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    focus, radius = viewing_region(dataset)
    # Seen by a good share of the rig, so from several sides: a voxel that only the cameras of one side see is
    # inside all their masks anywhere along the cone behind the subject.
    min_views = max(2, int(np.ceil(0.4 * len(cameras))))
    points = visual_hull(cameras, masks, focus - radius, focus + radius, resolution=resolution, min_views=min_views)
    if len(points) > count:
        points = points[np.sort(rng.choice(len(points), size=count, replace=False))]
    side = 2 * radius / resolution
    points = points + rng.uniform(-side / 2, side / 2, size=points.shape)
    images = [dataset.load_image(cam) for cam in cameras]
    return points.astype(np.float32), hull_colours(points, cameras, images, masks)


def viewing_region(dataset: Dataset) -> tuple[np.ndarray, float]:
    """(centre, radius) of the region the training cameras look at: the point closest (least squares)
    to all optical axes, and the median camera distance to it; where that point is no region they look at (parallel
    axes, or axes that cross behind the cameras), a point ahead of them along their mean viewing direction."""
    cams = {c.name: c for c in dataset.train}.values()
    A = np.zeros((3, 3))
    b = np.zeros(3)
    centre_list = []
    for cam in cams:
        d = cam.c2w[:3, 2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.center
        centre_list.append(cam.center)
    centres = np.array(centre_list)
    axes = np.array([c.c2w[:3, 2] for c in cams])
    try:
        focus = np.linalg.solve(A, b) if np.linalg.cond(A) < 1e8 else None
    except np.linalg.LinAlgError:
        focus = None
    # Axes (nearly) parallel, or crossing behind the cameras: the point of least squares is no region they look at.
    # Cameras that agree on a direction (a forward-facing rig, one camera): ahead of them along it, by the rig's
    # size (1 unit for a single camera, which has no scale of its own). Cameras looking outwards: a region around the
    # rig reaching past it, which each camera sees part of.
    if focus is None or np.median(np.einsum("ij,ij->i", focus - centres, axes)) <= 0:
        direction = axes.mean(axis=0)
        norm = float(np.linalg.norm(direction))
        size = dataset.scene_extent() or 1.0
        if norm > 0.5:
            focus = centres.mean(axis=0) + direction / norm * size
        else:
            focus = centres.mean(axis=0)
            return focus, 2.0 * size
    radius = float(np.median(np.linalg.norm(centres - focus, axis=1))) or 1.0
    return focus, radius


def random_points(dataset: Dataset, frame: int, count: int,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`count` points drawn uniformly in a cube around the viewing region, kept where at least two training
    cameras of `frame` see them, coloured from the first camera that sees each point."""
    warnings.warn(f"{dataset.name}: initialising frame {frame} with {count} random points (no data points or "
                  "triangulation); expect slower, worse training", stacklevel=3)
    focus, radius = viewing_region(dataset)
    cams = dataset.train_at(frame)
    if not cams:
        raise DataError(dataset.root, f"frame {frame} has no training camera to see random points")
    xyz_out, rgb_out = [], []
    got = 0
    for _ in range(50):
        xyz = focus + rng.uniform(-radius, radius, size=(4 * count, 3))
        seen = np.zeros(len(xyz), dtype=int)
        rgb = np.full((len(xyz), 3), np.nan)
        for cam in cams:
            uv, depth = cam.project(xyz)
            inside = (depth > 0.05 * radius) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (
                uv[:, 1] < cam.height)
            seen += inside
            fill = inside & np.isnan(rgb[:, 0])
            if fill.any():
                image = dataset.load_image(cam)
                px = uv[fill].astype(int)
                rgb[fill] = image[px[:, 1], px[:, 0]] / 255.0
        keep = seen >= min(2, len(cams))
        xyz_out.append(xyz[keep])
        rgb_out.append(rgb[keep])
        got += int(keep.sum())
        if got >= count:
            break
    xyz = np.concatenate(xyz_out)[:count]
    rgb = np.concatenate(rgb_out)[:count]
    if len(xyz) == 0:
        raise DataError(dataset.root, "no random point is seen by two training cameras: check the poses")
    return xyz.astype(np.float32), rgb.astype(np.float32)


def _frame_list(frames: list[int]) -> str:
    return ", ".join(map(str, frames[:8])) + (f" and {len(frames) - 8} more" if len(frames) > 8 else "")
