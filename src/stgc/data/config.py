"""Options of the data stage (path-independent; the dataset path is given separately)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal, get_args

from stgc.config import ConfigError, check, from_saved, validate_config
from stgc.errors import DataError, FormatError
from stgc.fileio import read_json_object
from stgc.run import Run, official_run_args

from .dataset import Dataset
from .points import InitSource, PointCloud, initial_points, thin_like
from .preprocess import PreprocessMode, PreprocessReport, preprocess_points
from .readers import format_names, open_dataset, resolve_format

# Enumerated options: each set is written once, as the field's type (the CLI's choices and validation follow it).
Background = Literal["black", "white"]
YuvRange = Literal["limited", "full"]


@dataclass
class DataConfig:
    format: str = field(default="auto", metadata={
        "help": "dataset layout: auto (detect from the files), panoptic, blender, n3dv, stg-colmap, technicolor, miv"})
    downscale: float = field(default=1.0, metadata={
        "help": "divide image width and height by this, rounded to whole pixels (an area average where a whole "
                "number divides both; Lanczos otherwise); K is scaled by the ratios achieved"})
    start: int | None = field(default=None, metadata={
        "help": "first frame of the segment (absolute index); default: the first frame of the data"})
    duration: int | None = field(default=None, metadata={
        "help": "number of frames in the segment (STG uses 50); default: all frames from start"})
    test_cameras: str | None = field(default=None, metadata={
        "help": "comma-separated held-out view names; default: the format's (cam00 N3DV/COLMAP, cam10 "
                "Technicolor, 0,10,15,30 Panoptic, v06,v08 MIV, transforms_test views Blender)"})
    fps: float | None = field(default=None, metadata={
        "help": "frame rate of the video; default: what the format states, else 30"})
    init_source: InitSource = field(default="auto", metadata={
        "help": "initial points: auto (data points, else triangulation, else random), data, triangulate, random"})
    init_frames_every: int = field(default=1, metadata={
        "help": "take initial points from every k-th frame of the segment (1 = all frames, as STG)"})
    max_points_per_frame: int | None = field(default=None, metadata={
        "help": "random subsample of each frame's initial points to at most this many (None = keep all)"})
    mask_points_per_frame: int = field(default=1000, metadata={
        "help": "where the data has foreground masks (Panoptic seg/), add up to this many initial points per frame "
                "inside the masks' visual hull: the moving subjects, which triangulation misses (0 = never)"})
    triangulation_upsample: float = field(default=2.0, metadata={
        "help": "upsample images by this factor before SIFT extraction (2 gives ~10x more points on small frames)"})
    min_track_length: int = field(default=3, metadata={
        "help": "keep triangulated points seen by at least this many images (track-2 points are mostly mismatches)"})
    triangulation_cache: bool = field(default=True, metadata={
        "help": "keep triangulated points on disk ($STGC_CACHE_DIR or ~/.cache/stgc) keyed by cameras, images and "
                "options, so a segment is triangulated once"})
    preprocess: PreprocessMode = field(default="none", metadata={
        "help": "point reduction before training: none, stg-isolated (official STG code: keep the ~25 percent most "
                "isolated points of every frame but the first), closest-pairs (paper: drop one point of each "
                "of the closest fraction of nearest-neighbour pairs)"})
    preprocess_fraction: float = field(default=0.25, metadata={
        "help": "fraction used by the preprocess rule (0.25 in STG and the paper)"})
    background: Background = field(default="black", metadata={
        "help": "colour that transparent pixels of RGBA images are composited on: black or white"})
    near_plane: float | None = field(default=None, metadata={
        "help": "view depth at or below which Gaussians are culled, in scene units; default: the format's (1.0 "
                "Panoptic, as Dynamic 3D Gaussians; 0.2 otherwise, as the official STG rasterizers)"})
    yuv_range: YuvRange = field(default="limited", metadata={
        "help": "MIV YUV sample range: limited (video, 16-235 at 8 bits) or full"})
    image_cache_mb: int = field(default=2048, metadata={
        "help": "memory bound of the decoded-image cache in MiB (least recently used images are dropped)"})
    seed: int = field(default=0, metadata={"help": "seed for subsampling and random initial points"})

    # How a run saved before these options existed was trained (stgc.config.from_saved): the official near plane
    # whatever the format, and no visual-hull points.
    SAVED_BEFORE: ClassVar[dict[str, Any]] = {"near_plane": 0.2, "mask_points_per_frame": 0}

    def validate(self, prefix: str = "") -> None:

        check(self.format == "auto" or resolve_format(self.format) is not None, f"{prefix}format", self.format,
              f"auto or one of {', '.join(format_names())}")
        check(math.isfinite(self.downscale) and self.downscale > 0, f"{prefix}downscale", self.downscale, "> 0")
        check(self.start is None or self.start >= 0, f"{prefix}start", self.start, ">= 0")
        check(self.duration is None or self.duration >= 1, f"{prefix}duration", self.duration, ">= 1")
        check(self.fps is None or (math.isfinite(self.fps) and self.fps > 0), f"{prefix}fps", self.fps, "> 0")
        sources = get_args(InitSource)
        check(self.init_source in sources, f"{prefix}init_source", self.init_source, f"one of {', '.join(sources)}")
        check(self.init_frames_every >= 1, f"{prefix}init_frames_every", self.init_frames_every, ">= 1")
        check(self.max_points_per_frame is None or self.max_points_per_frame >= 1, f"{prefix}max_points_per_frame",
              self.max_points_per_frame, ">= 1, or none")
        check(self.mask_points_per_frame >= 0, f"{prefix}mask_points_per_frame", self.mask_points_per_frame, ">= 0")
        check(math.isfinite(self.triangulation_upsample) and self.triangulation_upsample > 0,
              f"{prefix}triangulation_upsample", self.triangulation_upsample, "a finite number > 0")
        check(self.seed >= 0, f"{prefix}seed", self.seed, ">= 0")
        check(self.min_track_length >= 2, f"{prefix}min_track_length", self.min_track_length, ">= 2")
        modes = get_args(PreprocessMode)
        check(self.preprocess in modes, f"{prefix}preprocess", self.preprocess, f"one of {', '.join(modes)}")
        check(0 < self.preprocess_fraction < 1, f"{prefix}preprocess_fraction", self.preprocess_fraction, "in (0, 1)")
        check(self.near_plane is None or (math.isfinite(self.near_plane) and self.near_plane > 0),
              f"{prefix}near_plane", self.near_plane, "a depth > 0, or none for the format's")
        for name, kind in (("background", Background), ("yuv_range", YuvRange)):
            allowed = get_args(kind)
            check(getattr(self, name) in allowed, f"{prefix}{name}", getattr(self, name), " or ".join(allowed))
        check(self.image_cache_mb >= 0, f"{prefix}image_cache_mb", self.image_cache_mb, ">= 0")

    def open(self, path: str | Path) -> Dataset:
        """Open `path` with these options."""
        return open_dataset(path, format=self.format, downscale=self.downscale, start=self.start,
                            duration=self.duration, test_cameras=self.test_cameras, fps=self.fps,
                            image_cache_mb=self.image_cache_mb, background=self.background,
                            yuv_range=self.yuv_range, near_plane=self.near_plane)

    def points_ship_with(self, dataset: Dataset) -> bool:
        """Whether training starts from the points the data ships (an SfM/MVS cloud per frame, as STG's datasets
        have), rather than from points stgc triangulates or samples itself (a sparse cloud)."""
        return self.init_source == "data" or (self.init_source == "auto" and dataset.has_points)

    def initial_points(self, dataset: Dataset) -> tuple[PointCloud, PreprocessReport]:
        """Initial points of `dataset` with these options: (cloud, report).

        The preprocess rule sees each frame's whole cloud, as in STG (its "most isolated 25 %" means isolated
        within the real cloud, not within a random sample of it); the `max_points_per_frame` cap then thins what
        the rule kept by the factor the cap would have applied to the raw frame, min(1, cap / raw count). So a
        capped run keeps the rule's selection and its reduction ratio, at the capped scale. (Capping first would make
        the rule pick points isolated by the sampling, not by the scene.)"""
        frames = dataset.train_frames[:: max(1, self.init_frames_every)]
        kwargs = {} if self.max_points_per_frame is None else {"random_points_per_frame": self.max_points_per_frame}
        raw = initial_points(dataset, source=self.init_source, frames=frames, seed=self.seed,
                             triangulation_upsample=self.triangulation_upsample,
                             min_track_length=self.min_track_length,
                             triangulation_cache=self.triangulation_cache,
                             mask_points_per_frame=self.mask_points_per_frame, **kwargs)
        kept, report = preprocess_points(raw, self.preprocess, self.preprocess_fraction)
        return thin_like(kept, raw, self.max_points_per_frame, self.seed), report


def data_config_from_saved(section: dict[str, Any], source: str | Path | None) -> tuple[DataConfig, str | None]:
    """(DataConfig, dataset path) from the `data` section a run saved (RUN/config.json, or the copy a .stgc file
    embeds), read strictly: an unknown or ill-typed key is a FormatError naming `source`, never dropped."""
    if not isinstance(section, dict):
        raise FormatError(source, "the run config's 'data' section is not an object")
    section = dict(section)
    path = section.pop("path", None)
    try:
        return validate_config(from_saved(DataConfig, section, "data"), "data"), path
    except ConfigError as exc:
        raise FormatError(source, f"run config: {exc}") from None


def saved_run_data(run_dir: str | Path) -> tuple[DataConfig, str | None] | None:
    """(DataConfig, dataset path) that the run in `run_dir` saved in its config.json, or None without one."""
    run = Run(run_dir)
    saved = run.read_config()
    return None if saved is None else data_config_from_saved(saved.get("data") or {}, run.config_path)


def open_run_dataset(run_dir: str | Path, data_path: str | Path | None = None) -> Dataset:
    """The dataset the run in `run_dir` trained on, opened with its own saved data options (RUN/config.json);
    `data_path` replaces the saved location (the same data moved, or other data)."""
    config_path = Run(run_dir).config_path
    saved = saved_run_data(run_dir)
    if saved is None:
        if data_path is not None:  # a model without its run: the given data, with default options
            return _official_run_data_config(run_dir).open(data_path)
        raise DataError(config_path, "no run config found; pass the dataset with --data")
    config, path = saved
    target = data_path if data_path is not None else path
    if target is None:
        raise DataError(config_path, "config.json has no data.path; pass the dataset with --data")
    return config.open(target)


def _official_run_data_config(run_dir: str | Path) -> DataConfig:
    """Data options for a model without stgc's config.json: default ones, except that an official STG run's
    cfg_args gives its `duration` (its model's times are (frame - start) / duration: opened with every frame of the
    folder, t would be scaled by the wrong length), and a whole video's segment restored from a file without its
    run's config keeps its frames (restored_from.json: `start`, `duration`)."""
    restored = read_json_object(Path(run_dir) / Run.RESTORED_FROM) or {}
    first, length = restored.get("start"), restored.get("duration")
    if (isinstance(first, int) and isinstance(length, int) and not isinstance(first, bool)
            and not isinstance(length, bool) and first >= 0 and length > 0):
        return DataConfig(start=first, duration=length)
    official = official_run_args(run_dir)
    duration = None if official is None else official.get("duration")
    if isinstance(duration, int) and not isinstance(duration, bool) and duration > 0:
        logging.getLogger(__name__).info("%s: an official STG run of %d frames (cfg_args): frames 0-%d",
                                         run_dir, duration, duration - 1)
        return DataConfig(duration=duration)
    return DataConfig()


def initial_points_from_config(dataset: Dataset, cfg: DataConfig | None = None) -> PointCloud:
    """The trainer's entry point: initial points of `dataset` as `cfg` asks, after preprocessing (PointCloud).

    The per-frame counts before/after preprocessing are logged at INFO level."""
    cloud, report = (cfg or DataConfig()).initial_points(dataset)
    logging.getLogger(__name__).info("initial points: %d -> %d after preprocess %r -> %d after the per-frame cap",
                                     report.before, report.after, report.mode, len(cloud))
    return cloud
