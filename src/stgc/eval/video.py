"""Stills, videos and contact sheets of a trained model.

- `render_still`: one camera of the dataset at any time t -> PNG.
- `render_video`: a fixed camera over a frame range, or an orbit: a smooth path through the training cameras
  (centres on a cubic spline over chord length, orientations by slerp, the dataset's intrinsics) while time
  sweeps [0, 1] -> MP4 (imageio-ffmpeg, H.264) or GIF.
- `contact_sheet`: ground truth beside render for a few frames of the test views -> PNG.
Every file is written through `stgc.fileio.atomic_path`, so a reader never sees half a video.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import imageio.v2 as imageio
import numpy as np
import torch
from PIL import Image
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, Slerp

from stgc.codec import is_video_stgc, load_model
from stgc.data.cameras import Camera
from stgc.data.dataset import Dataset
from stgc.errors import DataError
from stgc.eval.evaluate import open_run_dataset, video_bitstream_segments
from stgc.fileio import atomic_path
from stgc.model import STGModel
from stgc.run import Run

log = logging.getLogger(__name__)

# A model to render: a run directory, an iteration folder, a PLY or a .stgc bitstream, or one in memory.
ModelSource = str | Path | STGModel


# ------------------------------------------------------------------------------------------------ loading
def load_model_and_dataset(run_or_model: ModelSource, dataset: Dataset | None = None,
                           data_path: str | Path | None = None) -> tuple[STGModel, Dataset]:
    """(model, dataset) from a run directory / iteration dir / PLY path / `.stgc` bitstream, or an in-memory model.
    A bitstream renders what it decodes to, with the dataset of the run beside it or of the config it embeds.
    `data_path` replaces the saved data location (data moved; a model without stgc's run config: an official
    run, or a bitstream written without its config, is opened on it with default data options)."""
    if isinstance(run_or_model, (str, Path)):
        path = Path(run_or_model)
        if (path.suffix == ".stgc" and is_video_stgc(path)) or Run(path).is_video():
            raise DataError(path, "a whole video: each segment is its own model; name one segment's run "
                                  "(RUN/segment_<k>, or `stgc decompress` the .stgc first), or render the whole "
                                  "as a video (.mp4, played across its segments)")
        if path.suffix == ".stgc":
            model = load_model(path)
            if dataset is None:
                dataset = open_run_dataset(path.parent, data_path, path)
            return model, dataset
        model = STGModel.load(path)
        if dataset is None:
            run = Run.of(path)
            if run is None and data_path is None:
                raise DataError(path, "cannot find the run's config.json: pass the dataset with --data")
            dataset = open_run_dataset(run.path if run is not None else path, data_path)
        return model, dataset
    if dataset is None:
        raise ValueError("rendering an in-memory model needs the dataset (for cameras and intrinsics)")
    return run_or_model, dataset


def find_camera(dataset: Dataset, camera_name: str, time: float | None = None) -> Camera:
    """The dataset camera named `camera_name` (train or test) whose frame time is nearest `time`, with its time
    set to `time` (so any t in [0, 1] can be rendered, not only frame times)."""
    matches = [c for c in [*dataset.test, *dataset.train] if str(c.name) == str(camera_name)]
    if not matches:
        names = sorted({str(c.name) for c in [*dataset.test, *dataset.train]})
        raise DataError(None, f"no camera named {camera_name!r}; cameras are {', '.join(names)}")
    if time is None:
        return matches[0]
    if not (0.0 <= float(time) <= 1.0):  # also false for nan
        raise DataError(None, f"time {time} is outside the model's [0, 1] (0 = first frame, 1 = end of the segment)")
    best = min(matches, key=lambda c: abs(float(c.time) - float(time)))
    return dataclasses.replace(best, time=float(time))


@torch.no_grad()
def render_image(model: STGModel, camera: Camera, time: float | None = None, background: Sequence[float] | None = None) -> np.ndarray:
    """uint8 [H, W, 3] render of `camera` at `time` (default the camera's), clamped to [0, 1]."""
    t = float(camera.time if time is None else time)
    rgb = model.render(camera, t=t, background=None if background is None else torch.tensor(background)).rgb
    return (rgb.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


# ------------------------------------------------------------------------------------------------ writers
def write_png(path: str | Path, image: np.ndarray) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(image)).save(tmp, format="PNG")
    return path


def _even(image: np.ndarray) -> np.ndarray:
    """H.264 with 4:2:0 chroma needs even sizes: pad odd ones by one edge row/column."""
    h, w = image.shape[:2]
    return np.pad(image, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge") if (h % 2 or w % 2) else image


def write_video(path: str | Path, frames: Iterable[np.ndarray], fps: float) -> Path:
    """MP4 (H.264, yuv420p) or GIF by the suffix of `path`; atomic."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".gif", ".mp4", ".mov", ".mkv"):
        raise ValueError(f"{path}: unsupported video type {suffix!r} (use .mp4 or .gif)")
    with atomic_path(path) as tmp:
        # imageio picks the container from the file name, so write under the real suffix, then move the finished
        # file onto the atomic temporary.
        named = tmp.with_name(tmp.name + suffix)
        try:
            if suffix == ".gif":
                # Browsers play a delay under 20 ms as 100 ms: above 50 fps every k-th frame is kept, at fps / k.
                step = max(1, math.ceil(fps / GIF_MAX_FPS - 1e-9))
                if step > 1:
                    log.info("%s: browsers play a GIF at up to %d fps: one frame in %d kept (%.3g fps)", path,
                             GIF_MAX_FPS, step, fps / step)
                images: list[Any] = [np.asarray(f) for k, f in enumerate(frames) if k % step == 0]
                imageio.mimsave(named, images, duration=_gif_delays_ms(len(images), fps / step), loop=0)
            else:
                # macro_block_size=2 keeps imageio from rescaling small frames to multiples of 16.
                writer = imageio.get_writer(named, fps=fps, codec="libx264", quality=8,
                                            pixelformat="yuv420p", macro_block_size=2)
                try:
                    for f in frames:
                        writer.append_data(_even(np.asarray(f)))
                finally:
                    writer.close()
            os.replace(named, tmp)
        finally:
            if named.exists():
                named.unlink()
    return path


GIF_MAX_FPS = 50  # delays of 20 ms; browsers show 10 ms or less as 100 ms


def _gif_delays_ms(count: int, fps: float) -> list[int]:
    """Per-frame GIF delays: the format stores hundredths of a second, so one delay 1000/fps ms would round (30 fps:
    30 ms, an 11 % faster video); delays that alternate keep every frame within 10 ms of its time."""
    ends = np.round(np.arange(1, count + 1) * 100.0 / fps)
    return [int(10 * d) for d in np.diff(ends, prepend=0.0)]


# ------------------------------------------------------------------------------------------------ paths
def _principal_angle_order(centers: np.ndarray) -> np.ndarray:
    """Order cameras around the rig: by angle in the plane of the two main axes of their centres (works for arcs
    and rings; a plain name order is arbitrary for many datasets)."""
    centred = centers - centers.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    u, v = centred @ vt[0], centred @ vt[1]
    angles = np.arctan2(v, u)
    order = np.argsort(angles)
    # Start after the largest angular gap, so an arc is traversed end to end rather than across its opening.
    sorted_angles = angles[order]
    gaps = np.diff(np.concatenate([sorted_angles, sorted_angles[:1] + 2 * np.pi]))
    start = (int(np.argmax(gaps)) + 1) % len(order)
    return np.roll(order, -start)


def orbit_cameras(dataset: Dataset, num_frames: int) -> list[Camera]:
    """`num_frames` cameras on a smooth path through the training cameras (one per view, frame 0 poses).

    Centres follow a cubic spline parameterised by chord length, orientations are slerped between neighbouring
    cameras at the same parameter, intrinsics and size are those of the first training camera; time sweeps from
    the first frame's time to the last frame's along the path (t = 1 lies one frame past the data)."""
    if num_frames < 1:
        raise ValueError("an orbit needs at least one frame")
    by_name: dict[str, Any] = {}
    for cam in dataset.train:
        by_name.setdefault(str(cam.name), cam)
    views = list(by_name.values())
    if len(views) < 2:
        raise DataError(None, "an orbit needs at least two training cameras")
    centers = np.array([c.center for c in views])
    views = [views[i] for i in _principal_angle_order(centers)]
    centers = np.array([c.center for c in views])
    chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centers, axis=0), axis=1))])
    # Coincident centres would make the parameter non-increasing; nudge them apart.
    chord = chord + np.arange(len(chord)) * 1e-9
    u = chord / chord[-1]
    spline = CubicSpline(u, centers, bc_type="natural") if len(views) > 2 else None
    rotations = Rotation.from_matrix(np.array([c.w2c[:3, :3].T for c in views]))  # camera-to-world rotations
    slerp = Slerp(u, rotations)
    s = np.linspace(0.0, 1.0, num_frames)
    path_centers = spline(s) if spline is not None else np.outer(1 - s, centers[0]) + np.outer(s, centers[1])
    path_rot = slerp(s).as_matrix()
    ref = views[0]
    first_time, last_time = dataset.time_of(min(dataset.frames)), dataset.time_of(max(dataset.frames))
    cams = []
    for i in range(num_frames):
        R_w2c = path_rot[i].T
        w2c = np.eye(4)
        w2c[:3, :3] = R_w2c
        w2c[:3, 3] = -R_w2c @ path_centers[i]
        t = float(first_time + s[i] * (last_time - first_time))
        cams.append(dataclasses.replace(ref, name=f"orbit{i:04d}", frame=i, time=t, w2c=w2c, image=None))
    return cams


def frame_selection(frames: Any, available: Sequence[int]) -> list[int]:
    """The frames of `available` that `frames` picks: None (all), "A:B", "A,B,...", a slice or a list; a
    DataError names a selection outside the dataset. A list keeps its order and its repeats (a clip may play a
    frame again); callers that write one file per frame drop the repeats themselves."""
    if frames is None:
        return list(available)
    if isinstance(frames, str):
        try:
            if ":" in frames:
                a, b = frames.split(":", 1)
                frames = slice(int(a) if a else None, int(b) if b else None)
            else:
                frames = [int(x) for x in frames.split(",") if x.strip()]
        except ValueError:
            raise DataError(None, f"frames {frames!r}: expected A:B or A,B,... of frame numbers") from None
    if isinstance(frames, slice):
        lo = frames.start if frames.start is not None else min(available)
        hi = frames.stop if frames.stop is not None else max(available) + 1
        if lo >= hi:  # A:A is not outside the frames: it holds none (was reported as outside them)
            raise DataError(None, f"frames {lo}:{hi} is empty: A:B takes frames A to B-1 (frame {lo} alone is "
                                  f"{lo}:{lo + 1}; dataset frames {min(available)}:{max(available) + 1})")
        if lo < min(available) or hi > max(available) + 1:
            raise DataError(None, f"frames {lo}:{hi} are not within the dataset's frames "
                                  f"{min(available)}:{max(available) + 1}")
        chosen = [f for f in available if lo <= f < hi]
    else:
        chosen = [int(f) for f in frames]
        missing = [f for f in chosen if f not in set(available)]
        if missing:
            raise DataError(None, f"frames {missing} are not in the dataset (frames {min(available)}..{max(available)})")
    if not chosen:
        raise DataError(None, f"frame selection {frames!r} is empty (dataset frames {min(available)}..{max(available)})")
    return chosen


def _camera_at(dataset: Dataset, name: str, frame: int) -> Camera:
    """The camera `name`'s view at `frame`. Monocular data has one view per image (each its own camera): there the
    named camera's pose is moved to the frame's time (a fixed novel view, as the viewer shows it; no image)."""
    for cam in [*dataset.test_at(frame), *dataset.train_at(frame)]:
        if str(cam.name) == str(name):
            return cam
    if not dataset.multiview:
        return dataclasses.replace(find_camera(dataset, name), frame=frame, time=float(dataset.time_of(frame)),
                                   image=None)
    raise DataError(None, f"camera {name!r} has no view at frame {frame}")


def _background(dataset: Dataset, background: Sequence[float] | None) -> Sequence[float]:
    """The colour asked for, else the dataset's (what training composited its images on)."""
    return tuple(dataset.background) if background is None else background


# ------------------------------------------------------------------------------------------------ public API
def render_still(
    run_or_model: ModelSource,
    camera_name: str,
    time: float,
    out_png: str | Path,
    *,
    dataset: Dataset | None = None,
    background: Sequence[float] | None = None,
) -> Path:
    """Render the dataset camera `camera_name` at time `time` in [0, 1] to `out_png`."""
    model, dataset = load_model_and_dataset(run_or_model, dataset)
    camera = find_camera(dataset, camera_name, time)
    return write_png(out_png, render_image(model, camera, time, _background(dataset, background)))


def render_video(
    run_or_model: ModelSource,
    out: str | Path,
    *,
    dataset: Dataset | None = None,
    camera_name: str | None = None,
    frames: Any = None,
    orbit: bool = False,
    num_frames: int | None = None,
    fps: float | None = None,
    background: Sequence[float] | None = None,
    data_path: str | Path | None = None,
) -> Path:
    """A video of the model (`data_path`: as `load_model_and_dataset`'s).

    Fixed view (default): `camera_name` (default the first test camera) at every frame in `frames` ("A:B",
    "0,5,9", a slice or a list of frame indices; default all), one video frame per dataset frame.
    orbit=True: `num_frames` (default 2 x dataset frames) views on a smooth path through the training cameras
    while time sweeps from the first frame's time to the last's. fps defaults to the dataset's.

    A whole-video run (`stgc train --segment-frames`) or whole-video .stgc plays across its segments: each frame
    is drawn by the segment that holds it (fixed view only)."""
    if isinstance(run_or_model, (str, Path)) and (Run(run_or_model).is_video() or is_video_stgc(run_or_model)):
        if orbit or dataset is not None:
            raise DataError(run_or_model, "a whole video renders from a fixed camera, each frame by its own "
                                          "segment (render one segment's run for an orbit)")
        if is_video_stgc(run_or_model):
            segments = [(s.model, s.dataset) for s in video_bitstream_segments(run_or_model, data_path)]
        else:
            segments = [load_model_and_dataset(segment.path, data_path=data_path)
                        for segment in Run(run_or_model).segments()]
        if not segments:
            raise DataError(run_or_model, "whole-video run without segments")
        return _render_across_segments(segments, out, camera_name, frames, fps, background)
    model, dataset = load_model_and_dataset(run_or_model, dataset, data_path)
    rate = float(fps or getattr(dataset, "fps", 30) or 30)
    if orbit:
        n = int(num_frames or 2 * len(list(dataset.frames)))
        cameras = orbit_cameras(dataset, n)
    else:
        name = camera_name or str((dataset.test or dataset.train)[0].name)
        cameras = [_camera_at(dataset, name, f) for f in frame_selection(frames, list(dataset.frames))]
    bg = _background(dataset, background)
    images = (render_image(model, cam, None, bg) for cam in cameras)
    return write_video(out, images, rate)


def _render_across_segments(segments: Sequence[tuple[STGModel, Dataset]], out: str | Path, camera_name: str | None,
                            frames: Any, fps: float | None, background: Sequence[float] | None) -> Path:
    holder: dict[int, tuple[STGModel, Dataset]] = {}  # each frame's segment (segments hold disjoint frames)
    for model, dataset in segments:
        for frame in dataset.frames:
            holder.setdefault(int(frame), (model, dataset))
    first = segments[0][1]
    name = camera_name or str((first.test or first.train)[0].name)
    rate = float(fps or getattr(first, "fps", 30) or 30)
    # In the selection's order, repeats kept, as for one model (frame_selection)
    images = (render_image(holder[f][0], _camera_at(holder[f][1], name, f), None, _background(holder[f][1], background))
              for f in frame_selection(frames, list(holder)))
    return write_video(out, images, rate)


def contact_sheet(
    model: STGModel,
    dataset: Dataset,
    frames: Any,
    out_png: str | Path,
    *,
    cameras: Sequence[str] | None = None,
    background: Sequence[float] | None = None,
    gap: int = 2,
) -> Path:
    """One row per (test camera, frame): ground truth | render | |error| x4, separated by `gap` black pixels."""
    model, dataset = load_model_and_dataset(model, dataset)
    names = list(cameras) if cameras else sorted({str(c.name) for c in dataset.test}) or [str(dataset.train[0].name)]
    rows = []
    background = _background(dataset, background)
    for frame in frame_selection(frames, list(dataset.frames)):
        if dataset.multiview:
            at_frame = names
        elif cameras:  # monocular data holds each view at one frame: the named ones this frame holds
            present = {str(c.name) for c in [*dataset.test_at(frame), *dataset.train_at(frame)]}
            at_frame = [name for name in names if name in present]
        else:  # this frame's own test views
            at_frame = [str(c.name) for c in dataset.test_at(frame)]
        for name in at_frame:
            cam = _camera_at(dataset, name, frame)
            gt = np.asarray(dataset.load_image(cam))[..., :3]
            pred = render_image(model, cam, None, background)
            err = np.clip(np.abs(gt.astype(np.int16) - pred.astype(np.int16)) * 4, 0, 255).astype(np.uint8)
            h = gt.shape[0]
            sep = np.zeros((h, gap, 3), np.uint8)
            rows.append(np.concatenate([gt, sep, pred, sep, err], axis=1))
    if not rows:
        raise DataError(None, f"no view to compare at frames {frames} (monocular data holds each image at one "
                              "frame: choose the frames of its test views, or of the cameras named)")
    width = rows[0].shape[1]
    sheet = []
    for r in rows:
        sheet += [r, np.zeros((gap, width, 3), np.uint8)]
    return write_png(out_png, np.concatenate(sheet[:-1], axis=0))
