"""`Dataset`: one multi-view video segment, the same object for every source format.

Readers (readers.py) describe everything a source holds at native resolution as a `SourceScene`;
`assemble` selects a frame segment, applies the downscale and the train/test split, and checks that
every view has every frame of the segment.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import imageio_ffmpeg
import numpy as np
from tqdm import tqdm

from ..errors import DataError
from .cameras import DEFAULT_NEAR_PLANE, Camera, ImageSource
from .images import ImageCache, image_size, read_image, resize_image
from .masks import read_mask
from .yuv import read_frame

DEFAULT_FPS = 30.0
DEFAULT_CACHE_BYTES = 2 << 30


_WHOLE_FILE_BYTES = 64 << 20
_SAMPLED_CHUNKS, _CHUNK_BYTES = 16, 1 << 20


def file_digest(path: Path) -> str:
    """sha256 of a file's bytes; of a file over 64 MiB (a whole video, a raw YUV stream), of its size and 16 chunks
    of 1 MiB spread evenly over it, so that fingerprinting a large capture reads 16 MiB of it. A file that cannot be
    read digests as its error (training it then fails with the reader's message)."""
    try:
        size = path.stat().st_size
        digest = hashlib.sha256(str(size).encode())
        with open(path, "rb") as f:
            if size <= _WHOLE_FILE_BYTES:
                digest.update(f.read())
            else:
                for k in range(_SAMPLED_CHUNKS):
                    f.seek((size - _CHUNK_BYTES) * k // (_SAMPLED_CHUNKS - 1))
                    digest.update(f.read(_CHUNK_BYTES))
        return digest.hexdigest()
    except OSError as exc:
        return f"unreadable: {type(exc).__name__}"


@dataclass(frozen=True)
class VideoFrame:
    """Frame `index` (0-based) of a video file decoded with imageio-ffmpeg; callable -> uint8 RGB."""

    path: Path
    index: int

    def __call__(self) -> np.ndarray:
        return decode_video(self.path, [self.index])[self.index]


@dataclass(frozen=True)
class YuvFrame:
    """Frame `index` of a planar YUV 4:2:0 file; callable -> uint8 RGB."""

    path: Path
    index: int
    width: int
    height: int
    bit_depth: int
    color_range: str = "limited"

    def __call__(self) -> np.ndarray:
        return read_frame(self.path, self.width, self.height, self.index, self.bit_depth, self.color_range)


# Every coded frame once, in order (as OpenCV's read loop in STG's pre_n3d.py). ffmpeg's default for a raw pipe is a
# constant frame rate: a video stream that starts after the file does (an audio track first, an edit list) is padded
# with copies of its first frame, and irregular timestamps duplicate or drop frames, so frame k was not the k-th.
@functools.cache
def every_coded_frame() -> tuple[str, ...]:
    """-fps_mode (ffmpeg 5.1 on) or the -vsync it replaced, for the ffmpeg imageio-ffmpeg runs (a system one may be
    older)."""
    found = re.search(r"(\d+)\.(\d+)", imageio_ffmpeg.get_ffmpeg_version() or "")
    old = found is not None and (int(found.group(1)), int(found.group(2))) < (5, 1)
    return ("-vsync" if old else "-fps_mode", "passthrough")


def decode_video(path: Path, indices: list[int]) -> dict[int, np.ndarray]:
    """Decode the frames `indices` of a video in one sequential pass (uint8 RGB); frame k is the k-th coded frame."""
    wanted = set(indices)
    last = max(wanted)
    out: dict[int, np.ndarray] = {}
    try:
        reader = imageio_ffmpeg.read_frames(str(path), pix_fmt="rgb24", output_params=list(every_coded_frame()))
        meta = next(reader)
        width, height = meta["size"]
        for i, raw in enumerate(reader):
            if i in wanted:
                out[i] = np.frombuffer(raw, dtype=np.uint8).reshape(height, width, 3).copy()
            if i >= last:
                break
        reader.close()
    except (OSError, RuntimeError, StopIteration) as exc:
        raise DataError(path, f"cannot decode video: {exc}") from None
    missing = sorted(wanted - set(out))
    if missing:
        raise DataError(path, f"video ends before frame {missing[0]}")
    return out


@dataclass
class SourceScene:
    """What a reader found, at native resolution, before choosing a segment.

    cameras: one per (view, available frame); `time` is filled in by `assemble`.
    multiview: every view is expected to have every frame (False for monocular D-NeRF).
    points: frame -> (xyz float [M,3], rgb float [M,3] in [0,1]) of points shipped with the data, or None.
    near_plane: the culling depth this source's reference renderer is used with (see cameras.DEFAULT_NEAR_PLANE).
    synthetic: rendered images (every camera has the same response), not a real rig's.
    view_dependent_colour: whether this source's reference method lets colour change with the viewing direction
        (official STG: yes; Dynamic 3D Gaussians, Panoptic's reference, keeps one colour per Gaussian and time).
    masks: camera -> path of its foreground mask (0 background; 255, or 1 in a 0/1 or palette mask, foreground:
        masks.read_mask), or None where it has none.
    static_points: `points` is one cloud for the whole capture (not one per frame): it is given to the first frame
        of whichever segment is opened, so that every segment of a video starts from it.
    frame_positions: frame -> where it lies on the frame axis, for sources whose frames are ranks of times that are
        not evenly spaced (monocular D-NeRF, whose test images' times fall between the training images'); None:
        frame f lies at f. Time is then t = (position - start) / duration, so that every image is rendered at the
        moment its file names, not at its rank.
    official_config: the family of the official STG code's per-dataset training configs that trains this source's
        scenes ('n3dv', 'technicolor': `stgc.official`), or None for a source without one.
    """

    name: str
    format: str
    root: Path
    cameras: list[Camera]
    default_test: list[str]
    meta_file: Path
    fps: float | None = None
    multiview: bool = True
    points: Callable[[int], tuple[np.ndarray, np.ndarray] | None] | None = None
    points_description: str | None = None
    default_start: int | None = None
    near_plane: float = DEFAULT_NEAR_PLANE
    synthetic: bool = False
    view_dependent_colour: bool = True
    masks: Callable[[Camera], Path | None] | None = None
    notes: list[str] = field(default_factory=list)
    frame_positions: dict[int, float] | None = None
    static_points: bool = False
    official_config: str | None = None

    def time_of(self, frame: int, start: int, duration: int) -> float:
        """Normalised time of `frame` in the segment [start, start + duration) (the one rule; see Dataset).

        With frame positions the segment spans from its first frame's position to the next segment's first (the
        last segment: its own frames' spacing carried one frame on), so its frames' times stay in [0, 1)."""
        if self.frame_positions is None:
            return (frame - start) / duration
        positions = self.frame_positions
        origin = positions.get(start, start)
        end = start + duration
        if end in positions:
            span = positions[end] - origin
        else:
            last = max((k for k in positions if start <= k < end), default=start)
            span = (positions[last] - origin) * duration / (last - start) if last > start else duration
        return (positions.get(frame, frame) - origin) / span


def segments(total_frames: int, duration: int, first: int = 0) -> list[tuple[int, int]]:
    """Split frames [first, first + total_frames) into consecutive (start, duration) segments, as STG
    trains a 300-frame video as six 50-frame models; the last segment may be shorter."""
    if total_frames <= 0 or duration <= 0:
        raise ValueError("total_frames and duration must be positive")
    return [(s, min(duration, first + total_frames - s)) for s in range(first, first + total_frames, duration)]


class Dataset:
    """A segment of a multi-view video: cameras per (view, frame), lazily loaded images.

    Time convention (STG): t = (frame − start) / duration for frame in [start, start + duration); where the
    source's frames are ranks of unevenly spaced times, `frame` is the frame's position (SourceScene.frame_positions).
    """

    def __init__(self, scene: SourceScene, *, start: int, duration: int, frames: list[int], train: list[Camera],
                 test: list[Camera], downscale: float, native_size: dict[int, tuple[int, int]], fps: float,
                 cache_bytes: int, background: tuple[float, float, float],
                 test_cameras: list[str] | None = None, near_plane: float | None = None):
        self._scene = scene
        self.name = scene.name
        self.format = scene.format
        self.root = scene.root
        self.fps = fps
        self.start = start
        self.duration = duration
        self.frames = frames
        self.train = train
        self.test = test
        self.downscale = downscale
        self.background = background
        self._native_size = native_size  # id(camera) -> native (width, height) of its image source
        self._test_cameras = test_cameras  # the split as requested (None = the format's default)
        self._near_plane = near_plane  # as requested (None = the format's)
        self._cache = ImageCache(cache_bytes)
        self._train_by_frame = _group(train)
        self._test_by_frame = _group(test)

    # ------------------------------------------------------------------ cameras and time
    @property
    def times(self) -> list[float]:
        return [self.time_of(f) for f in self.frames]

    def time_of(self, frame: int) -> float:
        return self._scene.time_of(frame, self.start, self.duration)

    @property
    def train_frames(self) -> list[int]:
        """The frames some training camera sees (monocular data also has frames that only a test image holds)."""
        return [f for f in self.frames if self._train_by_frame.get(f)]

    def train_at(self, frame: int) -> list[Camera]:
        return self._train_by_frame.get(frame, [])

    def test_at(self, frame: int) -> list[Camera]:
        return self._test_by_frame.get(frame, [])

    @property
    def cameras(self) -> list[Camera]:
        return self.train + self.test

    @property
    def has_masks(self) -> bool:
        """Whether the source ships foreground masks: some training view of the first training frame has one (views
        without one are left out where masks are used, and the run says so). Judged by the first view alone, a
        missing mask of that view turned every other view's mask off, silently."""
        if self._scene.masks is None or not self.train:
            return False
        return any(self.mask_path(c) is not None for c in self.train_at(self.train[0].frame))

    def mask_path(self, camera: Camera) -> Path | None:
        """The file of `camera`'s foreground mask, or None where it has none."""
        return None if self._scene.masks is None else self._scene.masks(camera)

    def load_mask(self, camera: Camera) -> np.ndarray | None:
        """bool [H, W] foreground of `camera`'s mask at its (downscaled) size, or None where it has none."""
        path = self.mask_path(camera)
        return None if path is None else read_mask(path, camera.width, camera.height)

    @property
    def multiview(self) -> bool:
        """Every view has every frame (False for monocular data: each image its own view)."""
        return bool(self._scene.multiview)

    @property
    def synthetic(self) -> bool:
        """Rendered images (identical camera responses), not a real capture."""
        return self._scene.synthetic

    @property
    def view_dependent_colour(self) -> bool:
        """Whether this source's reference method models colour that changes with the viewing direction."""
        return self._scene.view_dependent_colour

    @property
    def official_config(self) -> str | None:
        """The official STG config family that trains this source's scenes (SourceScene.official_config)."""
        return self._scene.official_config

    @property
    def near_plane(self) -> float:
        """The culling depth every camera of this dataset renders with."""
        return (self.train or self.test)[0].near

    @property
    def train_views(self) -> list[str]:
        return _unique_names(self.train)

    @property
    def test_views(self) -> list[str]:
        return _unique_names(self.test)

    def scene_extent(self) -> float:
        """STG's cameras_extent: 1.1 × the largest distance of a train camera centre from their mean."""
        cams = self.train or self.test
        centres = np.stack([c.center for c in cams])
        return float(1.1 * np.linalg.norm(centres - centres.mean(axis=0), axis=1).max())

    def segment(self, start: int, duration: int) -> Dataset:
        """The same source, another frame segment (same downscale, split and cache size)."""
        return assemble(self._scene, downscale=self.downscale, start=start, duration=duration,
                        test_cameras=self._test_cameras, fps=self.fps, cache_bytes=self._cache.max_bytes,
                        background=self.background, near_plane=self._near_plane)

    # ------------------------------------------------------------------ images
    def verify_images(self, cameras: list[Camera] | None = None, progress: bool = False) -> int:
        """Decode the image files (and masks) of `cameras` (default all) once, so that a truncated or corrupt file
        is a DataError naming it now rather than an error in the middle of a training. The images go through
        `load_image`, so they stay in the dataset's cache for the training that follows. Video frames are left to
        their decoder. Returns how many files were decoded."""
        cams = [c for c in (self.cameras if cameras is None else cameras) if isinstance(c.image, (str, Path))]
        if progress:

            cams = tqdm(cams, desc="checking images", unit="image", leave=False)
        count = 0
        for cam in cams:
            self.load_image(cam)
            count += 1
            if self.load_mask(cam) is not None:
                count += 1
        return count

    @functools.cached_property
    def fingerprint(self) -> str:
        """sha256 of what training reads: every training and test view (camera name, frame, time, intrinsics, pose,
        size, rounded to 1e-6), the bytes of the files its pixels and its foreground mask come from (`file_digest`),
        not where they lie:
        the same data moved to another folder has the same fingerprint, another capture with the same cameras or a
        re-rendered frame has another. A view whose pixels come from code (a callable) counts by its geometry."""
        digest = hashlib.sha256(self.format.encode())
        files: dict[Path, str] = {}
        for role, views in (("train", self.train), ("test", self.test)):
            for camera in views:
                geometry = np.round(np.concatenate([np.ravel(camera.K), np.ravel(camera.w2c), [camera.time]]), 6)
                digest.update(f"{role}|{camera.name}|{camera.frame}|{camera.width}x{camera.height}|".encode())
                digest.update((geometry + 0.0).tobytes())  # + 0.0: -0.0 and 0.0 alike
                source = camera.image
                path = Path(source) if isinstance(source, (str, Path)) else getattr(source, "path", None)
                if path is not None:
                    if path not in files:
                        files[path] = file_digest(path)
                    digest.update(f"|{files[path]}|{getattr(source, 'index', '')}".encode())
                mask = self.mask_path(camera)  # training weighs its loss by the foreground mask
                if mask is not None:
                    digest.update(f"|mask {file_digest(Path(mask))}".encode())
        return digest.hexdigest()

    @property
    def image_cache_bytes(self) -> int:
        """The bound on the decoded images kept (data.image_cache_mb)."""
        return self._cache.max_bytes

    def load_image(self, camera: Camera) -> np.ndarray:
        """uint8 [H, W, 3] at the camera's (downscaled) size; a private copy of the cached image, so callers
        may modify it or hand it to torch.from_numpy."""
        return self._cache.get(_cache_key(camera), lambda: self._load_uncached(camera)).copy()

    def _load_uncached(self, camera: Camera) -> np.ndarray:
        source = camera.image
        if source is None:
            raise DataError(self.root, f"camera {camera.name} frame {camera.frame} has no image source")
        if isinstance(source, VideoFrame):
            self._decode_video_segment(camera)
            cached = self._cache.peek(_cache_key(camera))
            if cached is not None:
                return cached
        native = self._decode_source(source)
        return self._fit(native, camera, source)

    def _decode_source(self, source: ImageSource) -> np.ndarray:
        if isinstance(source, (str, Path)):
            return read_image(Path(source), self.background)
        image = source()
        return np.asarray(image, dtype=np.uint8)

    def _fit(self, native: np.ndarray, camera: Camera, source: ImageSource) -> np.ndarray:
        expected = self._native_size.get(id(camera))
        h, w = native.shape[:2]
        if expected is not None and (w, h) != expected:
            where = source.path if isinstance(source, VideoFrame) else source if isinstance(source, (str, Path)) else None
            raise DataError(where, f"image is {w}x{h} but {expected[0]}x{expected[1]} was expected "
                                   f"(camera {camera.name}, from {self._scene.meta_file.name})")
        if expected is None and abs(w / h - camera.width / camera.height) > 0.02:
            raise DataError(None, f"image of camera {camera.name} frame {camera.frame} is {w}x{h}, which cannot "
                                  f"be resized to {camera.width}x{camera.height} without distortion")
        return resize_image(native, camera.width, camera.height)

    def _decode_video_segment(self, camera: Camera) -> None:
        """Decode every frame of this camera's video in the segment in one pass into the cache: videos
        cannot be seeked cheaply, and training visits frames in random order."""
        same_view = [(c, c.image) for c in self.cameras if c.name == camera.name and isinstance(c.image, VideoFrame)]
        if not same_view:
            raise ValueError(f"camera {camera.name} does not come from a video")
        decoded = decode_video(same_view[0][1].path, [frame.index for _, frame in same_view])
        for cam, frame in same_view:
            image = self._fit(decoded[frame.index], cam, frame)
            self._cache.put(_cache_key(cam), image)

    def image_float(self, camera: Camera) -> np.ndarray:
        """float32 [H, W, 3] in [0, 1]."""
        return self.load_image(camera).astype(np.float32) / 255.0

    def clear_cache(self) -> None:
        self._cache.clear()

    # ------------------------------------------------------------------ points and summary
    @property
    def has_points(self) -> bool:
        return self._scene.points is not None

    @property
    def points_description(self) -> str | None:
        """Where the shipped points come from, in words (None without any)."""
        return self._scene.points_description

    def ships_points_for(self, frame: int) -> bool:
        """Whether the data's points are meant for `frame`: every frame's of per-frame points; a static cloud (one
        for the whole capture) belongs to the segment's first frame."""
        return self._scene.points is not None and not (self._scene.static_points and frame != self.start)

    def data_points(self, frame: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Points shipped with the data for `frame` (xyz, rgb in [0,1]), or None (`ships_points_for`; or a frame
        whose file is missing)."""
        if not self.ships_points_for(frame):
            return None
        assert self._scene.points is not None
        return self._scene.points(frame)

    def memory_bytes(self, dtype_bytes: int = 1) -> int:
        """Memory for all images of the segment (train + test) at `dtype_bytes` per channel."""
        return sum(c.width * c.height * 3 * dtype_bytes for c in self.cameras)

    def summary(self) -> dict[str, Any]:
        sizes = sorted({(c.width, c.height) for c in self.cameras})
        native = sorted(set(self._native_size.values()))
        return {
            "name": self.name,
            "format": self.format,
            "root": str(self.root),
            "fps": self.fps,
            "start": self.start,
            "duration": self.duration,
            "frames": [self.frames[0], self.frames[-1]] if self.frames else [],
            # whether time follows the source's time values (SourceScene.frame_positions), not STG's rule
            "times_from_positions": self._scene.frame_positions is not None,
            "times": [self.time_of(self.frames[0]), self.time_of(self.frames[-1])] if self.frames else [],
            "num_frames": len(self.frames),
            "views": len(self.train_views) + len(self.test_views),
            "train_views": self.train_views,
            "test_views": self.test_views,
            "train_images": len(self.train),
            "test_images": len(self.test),
            "resolution": [list(s) for s in sizes],
            "native_resolution": [list(s) for s in native],
            "downscale": self.downscale,
            "scene_extent": round(self.scene_extent(), 6),
            "memory_uint8_bytes": self.memory_bytes(1),
            "memory_float32_bytes": self.memory_bytes(4),
            "points": self._scene.points_description,
            "notes": list(self._scene.notes),
        }

    def __repr__(self) -> str:
        return (f"Dataset({self.name!r}, format={self.format!r}, frames=[{self.start}, {self.start + self.duration}), "
                f"train={len(self.train_views)} views, test={len(self.test_views)} views)")


def _cache_key(camera: Camera) -> tuple[str, int, int, int]:
    return (camera.name, camera.frame, camera.width, camera.height)


def _group(cameras: list[Camera]) -> dict[int, list[Camera]]:
    out: dict[int, list[Camera]] = {}
    for cam in cameras:
        out.setdefault(cam.frame, []).append(cam)
    return out


def _unique_names(cameras: list[Camera]) -> list[str]:
    return list(dict.fromkeys(c.name for c in cameras))


def assemble(scene: SourceScene, *, downscale: float = 1, start: int | None = None, duration: int | None = None,
             test_cameras: list[str] | str | None = None, fps: float | None = None,
             cache_bytes: int = DEFAULT_CACHE_BYTES, background: tuple[float, float, float] = (0.0, 0.0, 0.0),
             check_images: bool = True, near_plane: float | None = None) -> Dataset:
    """Select the segment [start, start + duration), split, downscale and check a `SourceScene`.

    near_plane: the culling depth of every camera (None: the format's, `scene.near_plane`)."""
    if not scene.cameras:
        raise DataError(scene.meta_file, "no cameras found")
    _check_unique(scene)
    available = sorted({c.frame for c in scene.cameras})
    if start is None:
        start = scene.default_start if scene.default_start is not None else available[0]
    if duration is None:
        duration = available[-1] + 1 - start
    if duration <= 0 or start > available[-1] or start + duration <= available[0]:
        raise DataError(scene.root, f"empty frame range: start={start}, duration={duration}, but the data holds "
                                    f"frames {available[0]}..{available[-1]}")
    frames = [f for f in available if start <= f < start + duration]
    if scene.multiview:
        wanted = list(range(start, start + duration))
        absent = sorted(set(wanted) - set(frames))
        if absent:
            raise DataError(scene.root, f"frames {_ranges(absent)} of the range [{start}, {start + duration}) are "
                                        f"not in the data (it holds {_ranges(available)})")
    if not frames:
        raise DataError(scene.root, f"empty frame range [{start}, {start + duration})")

    in_segment = [c for c in scene.cameras if start <= c.frame < start + duration]
    views = list(dict.fromkeys(c.name for c in scene.cameras))
    if scene.multiview:
        _check_complete(scene, in_segment, views, frames)

    if isinstance(test_cameras, str):
        test_cameras = [n.strip() for n in test_cameras.split(",") if n.strip()]
    test_names = list(scene.default_test if test_cameras is None else test_cameras)
    unknown = [n for n in test_names if n not in views]
    if unknown and test_cameras is not None:
        raise DataError(scene.meta_file, f"test camera(s) {unknown} not in the data (views: {views})")

    if downscale <= 0 or not math.isfinite(downscale):
        raise ValueError(f"downscale must be positive, not {downscale}")
    near = scene.near_plane if near_plane is None else float(near_plane)
    if not (near > 0 and math.isfinite(near)):
        raise ValueError(f"near_plane must be a positive depth, not {near_plane}")
    native_size: dict[int, tuple[int, int]] = {}
    train: list[Camera] = []
    test: list[Camera] = []
    for cam in in_segment:
        out = replace(cam, time=scene.time_of(cam.frame, start, duration), near=near)
        if downscale != 1:
            out = out.scaled(1.0 / downscale)
        native_size[id(out)] = (cam.width, cam.height)
        (test if cam.name in test_names else train).append(out)
    key = lambda c: (c.frame, views.index(c.name))
    train.sort(key=key)
    test.sort(key=key)
    if not train:
        raise DataError(scene.meta_file, f"no training cameras left after holding out {test_names}")

    dataset = Dataset(scene, start=start, duration=duration, frames=frames, train=train, test=test,
                      downscale=downscale, native_size=native_size, fps=float(fps or scene.fps or DEFAULT_FPS),
                      cache_bytes=cache_bytes, background=background,
                      test_cameras=None if test_cameras is None else list(test_cameras),
                      near_plane=None if near_plane is None else near)
    if check_images:
        _check_image_headers(dataset, native_size)
    return dataset


def _check_unique(scene: SourceScene) -> None:
    """One camera per (view, frame): a view listed twice for a frame would train (or be tested) twice on it, and
    both share one cache entry, so one of them shows the other's image. And one view per image: two views reading
    one file (or one frame of one video or YUV file) is a slip in the metadata, and where one of them is held out,
    the test scores a training image."""
    seen = set()
    owner: dict[tuple[str, int], Camera] = {}
    for c in scene.cameras:
        if (c.name, c.frame) in seen:
            raise DataError(scene.meta_file, f"camera {c.name} frame {c.frame} appears twice")
        seen.add((c.name, c.frame))
        source = _source_key(c.image)
        if source is None:
            continue
        other = owner.setdefault(source, c)
        if other.name != c.name:
            path, index = source
            what = f"frame {index} of this file is" if index >= 0 else "this file is"
            raise DataError(path, f"{what} the image of two views: camera {other.name} frame {other.frame} and "
                                  f"camera {c.name} frame {c.frame}; each view needs its own images, or a held-out "
                                  "view is tested on a training image")


def _source_key(image: ImageSource | None) -> tuple[str, int] | None:
    """(file, frame index within it; -1 for an image file) of a camera's pixels, None for other sources. The path is
    normalised lexically ('a/./b', 'a/../a/b'): no file system access per image."""
    if isinstance(image, (str, Path)):
        return os.path.normpath(image), -1
    if isinstance(image, (VideoFrame, YuvFrame)):
        return os.path.normpath(image.path), image.index
    return None


def _check_complete(scene: SourceScene, cameras: list[Camera], views: list[str], frames: list[int]) -> None:
    have = {(c.name, c.frame) for c in cameras}
    for view in views:
        missing = [f for f in frames if (view, f) not in have]
        if missing:
            raise DataError(scene.meta_file, f"camera {view} has no image for frame(s) {_ranges(missing)} "
                                             "that other cameras have (missing images)")


def _check_image_headers(dataset: Dataset, native_size: dict[int, tuple[int, int]]) -> None:
    """Fail early on missing, unreadable or wrongly sized image files: every file when there are few,
    else the first frame of each view (the rest are checked when loaded)."""
    files = [(c, Path(c.image)) for c in dataset.cameras if isinstance(c.image, (str, Path))]
    if len(files) > 5000:
        first: dict[str, tuple[Camera, Path]] = {}
        for cam, path in files:
            first.setdefault(cam.name, (cam, path))
        files = list(first.values())
    for cam, path in files:
        if not path.is_file():
            raise DataError(path, f"image file is missing (camera {cam.name}, frame {cam.frame})")
        w, h = image_size(path)
        if (w, h) != native_size[id(cam)]:
            ew, eh = native_size[id(cam)]
            raise DataError(path, f"image is {w}x{h} but {ew}x{eh} was expected (camera {cam.name}, "
                                  f"from {dataset._scene.meta_file.name})")


def _ranges(values: list[int]) -> str:
    """'0-4, 7, 9-10' for [0,1,2,3,4,7,9,10]."""
    values = sorted(values)
    parts, i = [], 0
    while i < len(values):
        j = i
        while j + 1 < len(values) and values[j + 1] == values[j] + 1:
            j += 1
        parts.append(str(values[i]) if i == j else f"{values[i]}-{values[j]}")
        i = j + 1
    return ", ".join(parts) if len(parts) <= 6 else ", ".join(parts[:6]) + ", ..."
