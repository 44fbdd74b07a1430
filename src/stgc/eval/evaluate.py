"""The evaluation driver: render every test camera at every frame, score it, time it, write RUN/eval.json.

STG protocol (`test.py`): the render is clamped to [0, 1], PSNR and SSIM are computed per image and averaged
over all test images (cameras x frames); FPS is 1 / mean render time after warm-up.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import json
import logging
import math
import re
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from stgc import machine
from stgc.codec import (
    is_video_stgc,
    load_model,
    load_video_segment,
    model_digest,
    read_stgc_metadata,
    read_video_index,
)
from stgc.codec.video import read_video_segment_metadata
from stgc.config import EXECUTION_OPTIONS, ConfigError, from_saved, same_place
from stgc.data.cameras import Camera
from stgc.data.config import DataConfig, data_config_from_saved, saved_run_data
from stgc.data.config import open_run_dataset as open_saved_run_dataset
from stgc.data.dataset import Dataset
from stgc.errors import DataError, StgcError
from stgc.eval.accounting import (
    ModelSize,
    RenderSpeed,
    bitstream_size,
    duration_seconds,
    model_size_of,
    size_of_saved_model,
    speed_from_times,
    training_seconds,
)
from stgc.fileio import atomic_open, atomic_path, file_sha256, read_json_object, write_json
from stgc.metrics import LPIPS, psnr, ssim, yuv_psnr
from stgc.metrics.image import PSNR_CEILING_DB
from stgc.model import ModelConfig, STGModel
from stgc.render import BACKENDS
from stgc.run import SAVED_MODEL, Run

log = logging.getLogger(__name__)

PER_VIEW_COLUMNS = ("camera", "frame", "time", "psnr", "ssim", "lpips", "render_ms", "psnr_yuv", "psnr_y", "psnr_u",
                    "psnr_v")
# MPEG's YUV-PSNR (`stgc.metrics.yuv_psnr`): the 6:1:1 combination, then per plane.
YUV_KEYS = ("psnr_yuv", "psnr_y", "psnr_u", "psnr_v")


@dataclass
class ViewScore:
    camera: str
    frame: int
    time: float
    psnr: float
    ssim: float
    lpips: float | None
    render_ms: float
    yuv: dict[str, float] = field(default_factory=dict)  # YUV_KEYS -> dB


@dataclass
class EvalResult:
    views: list[ViewScore]
    lpips_note: str
    speed: RenderSpeed | None
    per_camera: dict[str, dict[str, float | None]] = field(default_factory=dict)
    overall: dict[str, float | None] = field(default_factory=dict)

    @property
    def psnr(self) -> float:
        return float(self.overall["psnr"])  # type: ignore[arg-type]

    @property
    def ssim(self) -> float:
        return float(self.overall["ssim"])  # type: ignore[arg-type]




def _mean(values: Iterable[float | None], ceiling: float = math.inf) -> float | None:
    vals = [min(v, ceiling) for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def _aggregate(views: Sequence[ViewScore]) -> dict[str, float | None]:
    return {
        "psnr": _mean((v.psnr for v in views), PSNR_CEILING_DB),
        "ssim": _mean(v.ssim for v in views),
        "lpips": _mean(v.lpips for v in views),
        **{key: _mean((v.yuv.get(key) for v in views), PSNR_CEILING_DB) for key in YUV_KEYS},
        "views": len(views),
    }


def _as_image(rendered: Any) -> torch.Tensor:
    """A render result ([H,W,3] tensor/array, or an object with `.rgb` such as ModelRender) as float [H,W,3]."""
    if hasattr(rendered, "rgb"):
        rendered = rendered.rgb
    if isinstance(rendered, np.ndarray):
        rendered = torch.from_numpy(np.ascontiguousarray(rendered))
    if not isinstance(rendered, torch.Tensor):
        raise TypeError(f"render function returned {type(rendered).__name__}, expected an image tensor")
    rendered = rendered.detach().cpu()
    if rendered.dtype == torch.uint8:
        return rendered.float() / 255.0
    return rendered.float()


@torch.no_grad()
def evaluate(
    render_fn: Callable[[Camera], Any],
    cameras: Sequence[Camera],
    load_image: Callable[[Camera], np.ndarray],
    *,
    lpips_net: str | None = None,
    warmup: int = 2,
    clamp: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> EvalResult:
    """Score `render_fn(camera)` against `load_image(camera)` (uint8 [H,W,3]) for every camera.

    `cameras` holds one entry per test view *and frame* (Dataset.test). The first `warmup` render times are
    left out of the FPS figure. LPIPS is computed only when `lpips_net` is given and its weights are on this
    machine; otherwise `lpips_note` says why it was skipped."""
    if not cameras:
        raise ValueError("evaluate() needs at least one test camera")
    lpips_model, lpips_note = (None, "skipped: not requested") if lpips_net is None else LPIPS.create(lpips_net)
    views: list[ViewScore] = []
    times: list[float] = []
    for i, cam in enumerate(cameras):
        start = time.perf_counter()
        rendered = _as_image(render_fn(cam))
        elapsed = time.perf_counter() - start
        times.append(elapsed)
        if not bool(torch.isfinite(rendered).all()):  # NaN scored null PSNR (a perfect render's), NaN SSIM, real YUV
            raise StgcError(f"camera {cam.name} frame {cam.frame}: the render holds non-finite values (a diverged "
                            "model?); nothing scored")
        if clamp:
            rendered = rendered.clamp(0.0, 1.0)
        gt = torch.from_numpy(np.ascontiguousarray(load_image(cam)))
        gt = gt.float() / 255.0 if gt.dtype == torch.uint8 else gt.float()
        gt = gt[..., :3]
        if rendered.shape != gt.shape:
            raise DataError(
                cam.image if isinstance(cam.image, (str, Path)) else None,
                f"camera {cam.name} frame {cam.frame}: render is {tuple(rendered.shape)} but the ground-truth image "
                f"is {tuple(gt.shape)}",
            )
        views.append(
            ViewScore(
                camera=str(cam.name),
                frame=int(cam.frame),
                time=float(cam.time),
                psnr=float(psnr(rendered.double(), gt.double())),
                ssim=float(ssim(rendered, gt)),
                lpips=lpips_model(rendered, gt) if lpips_model is not None else None,
                render_ms=1e3 * elapsed,
                yuv={f"psnr_{k}": v for k, v in yuv_psnr(rendered, gt).items()},
            )
        )
        if progress:
            progress(i + 1, len(cameras))
    by_camera: dict[str, list[ViewScore]] = {}
    for v in views:
        by_camera.setdefault(v.camera, []).append(v)
    return EvalResult(
        views=views,
        lpips_note=lpips_note,
        speed=speed_from_times(times, min(warmup, max(0, len(times) - 1))),
        per_camera={name: _aggregate(vs) for name, vs in sorted(by_camera.items())},
        overall=_aggregate(views),
    )


def _finite(x: Any) -> Any:
    # JSON has no inf/nan: anything infinite left in a record (the means are capped at PSNR_CEILING_DB) is null.
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def eval_record(
    result: EvalResult, model_info: ModelSize | Mapping[str, Any] | None, extra: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """The eval.json object: overall metrics first, then size/rate, speed, per-camera aggregates."""
    info = model_info.as_dict() if isinstance(model_info, ModelSize) else dict(model_info or {})
    record: dict[str, Any] = {
        "psnr": _finite(result.overall["psnr"]),
        "ssim": result.overall["ssim"],
        "lpips": result.overall["lpips"],
        "lpips_note": result.lpips_note,
        **{key: _finite(result.overall.get(key)) for key in YUV_KEYS},
        "num_gaussians": info.get("num_gaussians"),
        "size_mb": info.get("size_mb"),
        "mbps": info.get("mbps"),
        "fps": result.speed.fps if result.speed else None,
        "num_views": len(result.views),
        "cameras": sorted({v.camera for v in result.views}),
        "frames": sorted({v.frame for v in result.views}),
    }
    record.update({k: v for k, v in info.items() if k not in record})
    record["render_speed"] = result.speed.as_dict() if result.speed else None
    record["per_camera"] = {k: {kk: _finite(vv) for kk, vv in v.items()} for k, v in result.per_camera.items()}
    record["units"] = {
        "size_mb": "MiB (2^20 bytes), the paper's 'MB'",
        "size_mb_si": "10^6 bytes",
        "mbps": "10^6 bits per second of video covered (= MiB x 8.388608 / seconds)",
        "fps": "renders per second after warm-up, this machine",
    }
    if extra:
        record.update(extra)
    return record


def write_eval(
    run_dir: str | Path,
    result: EvalResult,
    model_info: ModelSize | Mapping[str, Any] | None = None,
    *,
    target: str | Path | None = None,
    extra: Mapping[str, Any] | None = None,
    other_data: str | None = None,
) -> dict[str, Any]:
    """Write the evaluation record and its per-view CSV atomically (where `Run.eval_paths` puts them: of the run's
    model, or of the bitstream `target`, on the run's own data or `other_data`) and return the record
    (`format_eval_table` prints it). Training time is read from RUN/train_summary.json."""
    run = Run(run_dir)
    bitstream = target if target is not None and Path(target).suffix == ".stgc" else None
    json_path, csv_path = run.eval_paths(other_data, bitstream)
    summary = run.read_summary() if run.path.is_dir() else None
    more: dict[str, Any] = {"train_seconds": training_seconds(summary)}
    if summary and "iterations" in summary:
        more["iterations"] = summary["iterations"]
    if target is not None and bitstream is None:
        refuse_misfiled_model(Path(target))
    if bitstream is None and run.has_config():
        # Whether the model scored is the one the run ends with (a restored run's is: it came from a bitstream).
        more["training_finished"] = run.holds_final_model()
        restored = read_json_object(run.path / Run.RESTORED_FROM, strict=False)
        if restored is not None:
            more["restored_from"] = restored.get("bitstream")
    if bitstream is not None:
        more.update(bitstream=Path(bitstream).name, bitstream_sha256=file_sha256(bitstream))
        metadata = read_stgc_metadata(bitstream)
        # Another run's file copied into this folder was scored on its own test set and stamped with this run's
        # training time and final iteration: `stgc report` then showed it as this run's codec point.
        foreign = foreign_model(run, metadata)
        if foreign is not None:
            log.warning("%s holds the model of another run than %s (%s): its record says so, and reports leave it "
                        "out of this run's points", bitstream, run.path, foreign)
            more.update(foreign=foreign, train_seconds=None)
        # The model the file holds, which need not be the run's final one (`stgc compress RUN/point_cloud/
        # iteration_N`, or a half-trained run compressed and finished since): the report tells them apart.
        iteration = metadata.get("iteration")
        if isinstance(iteration, int):
            more["iterations"] = iteration
            final = run.final_iteration()  # None where the folder's run does not say (a whole video's folder)
            if final is not None and foreign is None:
                more["training_finished"] = iteration == final
    more.update(extra or {})
    record = eval_record(result, model_info, more)
    write_json(json_path, record)
    _write_per_view(csv_path, [(None, v) for v in result.views])
    return record


def _write_per_view(csv_path: Path, rows: Sequence[tuple[str | None, ViewScore]]) -> None:
    """The per-view CSV; with a leading `segment` column when the rows come from a whole video's segments."""
    segmented = any(name is not None for name, _ in rows)
    with atomic_open(csv_path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow((["segment"] if segmented else []) + list(PER_VIEW_COLUMNS))
        for name, v in rows:
            writer.writerow(([name] if segmented else []) + [
                v.camera, v.frame, f"{v.time:.6f}", _fmt(v.psnr, 4), _fmt(v.ssim, 5), _fmt(v.lpips, 5),
                _fmt(v.render_ms, 2), *(_fmt(v.yuv.get(k), 4) for k in YUV_KEYS)])


def _fmt(x: float | None, digits: int) -> str:
    if x is None:
        return ""
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    return f"{x:.{digits}f}"


def format_eval_table(record: Mapping[str, Any]) -> str:
    """A compact rich table of an eval.json record, as plain text."""
    table = Table(title="evaluation", show_header=True, header_style="bold")
    for col in ("camera (views)", "PSNR", "YUV-PSNR", "SSIM", "LPIPS", "#Gaussians", "size MiB", "Mbps", "FPS"):
        table.add_column(col, justify="right")

    def row(name: str, agg: Mapping[str, Any], sized: Mapping[str, Any] | None) -> None:
        table.add_row(
            f"{name} ({agg.get('views', agg.get('num_views', ''))})",
            _fmt(agg.get("psnr"), 2), _fmt(agg.get("psnr_yuv"), 2) or "-", _fmt(agg.get("ssim"), 4),
            _fmt(agg.get("lpips"), 4) or "-",
            f"{sized['num_gaussians']:,}" if sized and sized.get("num_gaussians") is not None else "",
            _fmt(sized.get("size_mb"), 2) if sized else "", _fmt(sized.get("mbps"), 2) if sized else "",
            _fmt(sized.get("fps"), 1) if sized else "",
        )

    # A whole video: a row per segment (each its own model); a single segment: a row per test camera.
    for name, agg in (record.get("per_segment") or {}).items():
        row(name, agg, agg)
    if not record.get("per_segment"):
        for name, agg in (record.get("per_camera") or {}).items():
            row(name, agg, None)
    row("all", {**record, "views": record.get("num_views")}, record)
    buf = io.StringIO()
    console = Console(file=buf, width=100, color_system=None, force_terminal=False)
    console.print(table)
    note = record.get("lpips_note")
    if note and record.get("lpips") is None:  # why it is missing
        console.print(f"LPIPS {note}")
    elif note and note != "available":  # which convention scored it (records before 2026-11-30 say "available")
        console.print(note)
    for seam in record.get("seams") or []:
        console.print(f"{seam['segment']}: frames {seam['first_frame']}-{seam['last_frame']}, PSNR first / middle / "
                      f"last {seam['psnr_first']:.2f} / {seam['psnr_middle']:.2f} / {seam['psnr_last']:.2f} dB "
                      f"(seam loss {seam['seam_loss_db']:+.2f} dB)")
    return buf.getvalue()


# ------------------------------------------------------------------------------------- whole runs


class RunEvaluator:
    """The trainer's test evaluation (`stgc.train.TestEvaluator`): every test camera x frame, and at the end of
    training the run's eval.json with the sizes of the files just saved, as `stgc eval RUN` would write it."""

    def score(self, render: Callable[[Camera], torch.Tensor], dataset: Dataset) -> EvalResult:
        return evaluate(render, dataset.test, dataset.load_image)

    def score_and_record(self, render: Callable[[Camera], torch.Tensor], dataset: Dataset, run: Run,
                         model: STGModel) -> EvalResult:
        result = self.score(render, dataset)
        saved = run.latest_model_dir()
        files = [] if saved is None else [saved / "point_cloud.ply", saved / "point_cloud.pt"]
        info: ModelSize | dict[str, Any]
        try:
            info = model_size_of(model, dataset_duration_s(dataset), files)
        except (ValueError, AttributeError, ZeroDivisionError):
            info = {"num_gaussians": model.num_gaussians}
        write_eval(run.path, result, info, extra=dataset_identity(dataset))
        return result


def open_run_dataset(run_dir: Path, data_path: str | Path | None = None, bitstream: Path | None = None) -> Any:
    """The dataset a run was trained on, opened with the run's own data options: RUN/config.json, or for a
    `.stgc` file the run config the encoder embedded in it (the folder the file lies in may hold another run: a
    segment's file written into its whole video's folder), else its folder's."""
    if bitstream is not None:
        metadata = read_stgc_metadata(bitstream)
        if embedded_data_section(metadata) is not None or not Run(run_dir).has_config():
            return open_embedded_dataset(metadata, bitstream, data_path)
        if Run(run_dir).is_video():
            # The video's config spans every segment's frames: a segment's model would be scored (and rendered) at
            # the whole video's times, on frames it was not trained on.
            raise DataError(bitstream, f"a single model's file without its run config (codec.embed_run_config="
                                       f"false) in the whole video's folder {run_dir}: which segment's frames it "
                                       "covers is unknown; put it in its segment's folder (segment_<k>/) or "
                                       "compress with the run config embedded")
    return open_saved_run_dataset(run_dir, data_path)


def embedded_data_section(metadata: Mapping[str, Any]) -> dict[str, Any] | None:
    """The `data` section of the run config a bitstream's metadata embeds, or None without one."""
    embedded = metadata.get("run_config")
    section = embedded.get("data") if isinstance(embedded, dict) else None
    return section if isinstance(section, dict) else None


def open_embedded_dataset(metadata: Mapping[str, Any], source: str | Path, data_path: str | Path | None = None,
                          frames: tuple[int, int] | None = None) -> Any:
    """The dataset named by the run config a bitstream embeds (its `run_config` metadata); `data_path` replaces
    the saved location. A bitstream written without its config (codec.embed_run_config=false) is opened on
    `data_path` with default data options, over `frames` (start, count: a whole video's segment) when given."""
    section = embedded_data_section(metadata)
    if section is None:
        if data_path is None:
            raise DataError(source, "no run config found beside or inside the bitstream; pass the dataset with "
                                    "--data")
        config = DataConfig() if frames is None else DataConfig(start=frames[0], duration=frames[1])
        dataset = config.open(data_path)
        # The file does not say which frames the model was trained on (its config is what would): a model of
        # another window is scored here on the wrong frames, so the frames used are named.
        log.warning("%s: no run config beside or inside it: %s opened with default data options, frames %s-%s "
                    "(a model trained on other frames or options needs its run config: compress with "
                    "codec.embed_run_config=true)", source, data_path, dataset.frames[0] if dataset.frames else "?",
                    dataset.frames[-1] if dataset.frames else "?")
        return dataset
    config, path = data_config_from_saved(section, source)
    target = data_path if data_path is not None else path
    if target is None:
        raise DataError(source, "the embedded run config has no data.path; pass the dataset with --data")
    return config.open(target)


@dataclass
class BitstreamSegment:
    """One segment of a whole-video .stgc, ready to render: its model, the dataset of its frames, its size."""

    name: str
    model: STGModel
    dataset: Dataset
    size: ModelSize
    run: Run | None  # the segment's training run, when the container lies in the whole-video run it came from


def video_bitstream_segments(path: str | Path, data_path: str | Path | None = None) -> Iterator[BitstreamSegment]:
    """The segments of a whole-video .stgc in time order, decoded one at a time (random access: each reads only
    its own bytes). A segment's dataset is the one its embedded run config names (`data_path` replaces its
    location), as for a single model's file; without one, its training run's when the file lies in the whole-video
    run it was written from (RUN/<name>.stgc; `data_path` relocates its data). The run beside the file is the
    segment's (its name and training time) only where its frames and data are the embedded ones: a container copied
    into another video's folder of the same frames is scored on its own data. A dataset whose frames are not the segment's is an error, never
    a silently shifted timeline."""
    path = Path(path)
    index = read_video_index(path)
    beside = Run(path.parent)
    # With --data too (the data moved, or other data): the segments' runs still give their data options and training
    # times, as a single model's run does for its file (without them a file written without its configs was scored
    # with default options, and the record lost its training time); `data_path` relocates their data.
    plan = beside.read_video()["segments"] if beside.is_video() else []
    # The run's segments when they are the file's (else another video's: the configs the file embeds are used).
    same = ([(int(s["start"]), int(s["duration"])) for s in plan]
            == [(e.first_frame, e.num_frames) for e in index.entries])
    runs = [Run(beside.path / str(s["name"])) for s in plan] if same else []
    for k, entry in enumerate(index.entries):
        model, decoded = load_video_segment(path, k, index)
        source = f"{path} segment {k}"
        run = runs[k] if runs else None
        embedded = embedded_data_section(decoded.metadata)
        if run is not None and embedded is not None and (run.read_config(strict=False) or {}).get("data") != embedded:
            run = None  # another video's segment of the same frames
        dataset = open_saved_run_dataset(run.path, data_path) if run and embedded is None else \
            open_embedded_dataset(decoded.metadata, source, data_path, (entry.first_frame, entry.num_frames))
        frames = sorted(int(f) for f in dataset.frames)
        if frames != list(range(entry.first_frame, entry.last_frame + 1)):
            raise DataError(source, f"covers frames {entry.first_frame}-{entry.last_frame}, but its dataset has frames "
                                    f"{frames[0]}-{frames[-1]}" if frames else "its dataset has no frames")
        size = ModelSize(model.num_gaussians, model.variant, entry.length, "file", dataset_duration_s(dataset), 0,
                         {f"{path.name} segment {k}": entry.length})
        yield BitstreamSegment(run.path.name if run else f"segment_{k:03d}", model, dataset, size, run)


def dataset_duration_s(dataset: Dataset) -> float:
    """Seconds of video the dataset's frame window covers (frames / fps)."""
    return duration_seconds(len(dataset.frames), float(dataset.fps))


def evaluate_run(
    target: str | Path,
    data_path: str | Path | None = None,
    *,
    lpips_net: str | None = None,
    warmup: int = 2,
    measure_fps: bool = True,
    load_model: Callable[[Path], Any] | None = None,
    open_dataset: Callable[[Path], Any] | None = None,
    filed_as: str | None = None,
) -> dict[str, Any]:
    """Evaluate a run directory (its latest iteration) or a `.stgc` bitstream inside a run directory, write
    the eval files (`Run.eval_paths`), and return the eval.json record (`format_eval_table` prints it). What
    `stgc eval RUN` does. With measure_fps=False the record's fps is null.

    `load_model` / `open_dataset` default to `stgc.model.STGModel.load` (or `stgc.codec.load_model` for .stgc)
    and the dataset named in RUN/config.json; tests inject fakes. `filed_as`: the name a whole video's segments file
    an evaluation on other data under (the video's, so that the video's record combines theirs)."""
    target = Path(target)
    # A file (a bitstream, or a saved model's PLY) is scored into the folder it lies in.
    run_dir = target.parent if target.is_file() or target.suffix == ".stgc" else target
    if not target.exists():
        raise DataError(target, "no such run directory or bitstream")
    if target.suffix != ".stgc" and Run(target).is_video():
        if load_model is not None or open_dataset is not None:
            raise DataError(target, "a whole-video run is evaluated on its own data, segment by segment")
        segments = Run(target).segments()
        for segment in segments:
            if not segment.holds_final_model():
                # A killed or failed segment still holds the models save_iterations wrote: half-trained, not the
                # video (as `stgc compress` refuses it).
                raise DataError(segment.path, "segment has not finished training (finish it with stgc train "
                                              "--resume)")
        # The segments share the video's data, so they file alike: under the video's name for it, never under one
        # their own earlier records chose (a second dataset of the same folder name made the video's record
        # combine the first's scores).
        other = _other_data(target, data_path)
        for segment in segments:
            evaluate_run(segment.path, data_path, lpips_net=lpips_net, warmup=warmup, measure_fps=measure_fps,
                         filed_as=other)
        return write_video_eval(target, other, data=None if other is None else Path(str(data_path)).resolve())
    if target.suffix == ".stgc" and is_video_stgc(target):
        if load_model is not None or open_dataset is not None:
            raise DataError(target, "a whole-video bitstream is evaluated segment by segment on its own data")
        return _evaluate_video_bitstream(target, data_path, lpips_net=lpips_net, warmup=warmup,
                                         measure_fps=measure_fps)
    # A saved model inside a run (RUN/point_cloud/iteration_<N>) is scored on its run's data, with its run's options;
    # its record stays beside it.
    owner = Run.of(target) if target.suffix != ".stgc" and not Run(target).has_config() else None
    if target.suffix != ".stgc":
        refuse_misfiled_model(target, owner)  # before the minutes of rendering, not after
    config_dir = owner.path if owner is not None else run_dir
    dataset = open_dataset(run_dir) if open_dataset else open_run_dataset(
        config_dir, data_path, target if target.suffix == ".stgc" else None)
    if load_model is None:
        load_model = _default_model_loader
    if owner is None and target.suffix != ".stgc" and Run(target).has_config() and not Run(target).holds_final_model():
        log.warning("%s has not finished training: scoring its latest saved model (the record says so)", target)
    model = load_model(target)
    duration_s = dataset_duration_s(dataset)
    if target.suffix == ".stgc":
        info = bitstream_size(target, model.num_gaussians, model.variant, duration_s)
    else:
        info = size_of_saved_model(target, duration_s)
    # With the threads and backend the run trained with, as its trainer's own evaluation: one table's FPS are then
    # comparable (its .stgc points' too).
    threads, backend = _run_execution(config_dir)
    with machine.threads(threads):
        result = _score_model(model, dataset, lpips_net=lpips_net, warmup=warmup, measure_fps=measure_fps,
                              backend=backend)
    other_data = filed_as if filed_as is not None else _other_data(
        run_dir, data_path, target if target.suffix == ".stgc" else None, config_dir)
    extra = {**dataset_identity(dataset), **({"other_data": other_data} if other_data else {})}
    return write_eval(run_dir, result, info, target=target, other_data=other_data, extra=extra)


_ITERATION_FOLDER = re.compile(r"iteration_\d+")


def refuse_misfiled_model(target: Path, owner: Run | None = None) -> None:
    """Refuse to score a model whose record would stand for another model. A model is scored into the eval.json
    of its folder (a file: the folder it lies in), and that record is the folder's own: RUN/eval.json is what
    `stgc report` and the experiment runner take for the run's result, RUN/point_cloud/iteration_<N>/eval.json
    that iteration's. So only a run, one of its saved iterations, or their point_cloud.ply may write one (or a
    folder in no run, and its point_cloud.ply); `owner` is the run holding the target (by default
    `Run.of(target)`). Any other (RUN/other.ply, another model copied in) replaced the run's record, stamped with
    the run's iterations; its decoder (other.pt) was not the one its size counted (point_cloud.pt) either."""
    if not target.exists() or target.suffix == ".stgc" or (target.is_dir() and Run(target).has_config()):
        return
    if owner is None:
        owner = Run.of(target)
    folder = target.resolve() if target.is_dir() else target.resolve().parent
    iteration = owner is not None and _ITERATION_FOLDER.fullmatch(folder.name) is not None and \
        folder.parent == owner.path / "point_cloud"
    if target.is_dir():
        if owner is None or owner.path == folder or iteration:
            return
    elif target.name == SAVED_MODEL and (owner is None or iteration):
        return
    whose = f"the run in {owner.path}" if owner is not None else "its folder"
    raise DataError(target, f"not a saved model of {whose}: scored, it would replace {folder / 'eval.json'} (that "
                            "folder's own record) with another model's numbers. stgc eval takes a run, one of its "
                            "saved iterations (point_cloud/iteration_<N>), or a .stgc file; to score this model, "
                            f"put it as {SAVED_MODEL} (its decoder as point_cloud.pt) in a folder outside any run "
                            "and evaluate that folder with --data")


def dataset_identity(dataset: Any) -> dict[str, Any]:
    """What an evaluation record names of the test set it scored, besides the `cameras` and `frames` it lists: the
    data folder and the downscale of its images (a report compares rates and PSNRs only where all of them agree),
    and the video's frame rate that its Mbps assume (`video_fps`: the data's, or 30 where the data states none)."""
    downscale = getattr(dataset, "downscale", None)
    if isinstance(downscale, bool) or not isinstance(downscale, (int, float)):
        downscale = None  # a stand-in dataset (tests) has none
    fps = getattr(dataset, "fps", None)
    return {"data": str(dataset.root), "downscale": None if downscale is None else float(downscale),
            "video_fps": float(fps) if isinstance(fps, (int, float)) and not isinstance(fps, bool) else None}


def foreign_model(run: Run, metadata: Mapping[str, Any]) -> str | None:
    """Why a bitstream whose metadata is `metadata` holds a model of another run than the one in `run` (the folder
    it lies in), or None where it is that run's or the files cannot tell (a folder holding no run, a file written
    without its config and digest). Compared: the sections the encoder embeds (`run_config`: data, model), as
    `config_differences` reads them, and the digest of the model it was compressed from (`source_digest`, files
    written since 2026-11-30) against the run's saved model of the file's iteration, which tells apart runs of one
    config but their training options (seeds, compaction cases)."""
    embedded = metadata.get("run_config")
    restored = (run.path / Run.RESTORED_FROM).is_file()
    saved = run.read_config(strict=False)
    if saved is None and restored and isinstance(embedded, dict):
        # Restored from a file without its run's config, the run compresses to files without one again.
        return "the run has no config (restored from a file without one), the file embeds one"
    if saved is not None and isinstance(embedded, dict):
        differences = config_differences(embedded, saved)
        if differences:
            return "; ".join(differences[:4]) + (" ..." if len(differences) > 4 else "")
    digest, iteration = metadata.get("source_digest"), metadata.get("iteration")
    # A restored run's model is the decoded one, not the PLY the file was compressed from. (A folder without a
    # config, an official run's, is compared too: the digest needs only its saved models.)
    if isinstance(digest, str) and isinstance(iteration, int) and not restored:
        saved_model = run.saved_iterations().get(iteration)
        own = None if saved_model is None else model_digest(saved_model)
        if own is not None and own != digest:
            return (f"compressed from another model than the run's of iteration {iteration} (the PLY digests "
                    f"{digest} and {own}), or the run's model was saved again since")
    return None


_SECTION_CLASSES: dict[str, type] = {"data": DataConfig, "model": ModelConfig}


def config_differences(embedded: Mapping[str, Any], saved: Mapping[str, Any]) -> list[str]:
    """The options by which the run config a bitstream embeds differs from a run's config.json, in the sections
    the encoder embeds: [] where they are one run's. Each section is read as a resume reads it (`from_saved`), so
    that keys a later stgc added to a resumed run's config.json are no difference; execution options (a resume may
    change them) are left out, and so is the data's path where one of the two no longer exists (the data moved:
    a run resumed there records the new place, the files compressed before it the old one)."""
    out = []
    for section, cls in _SECTION_CLASSES.items():
        mine, theirs = embedded.get(section), saved.get(section)
        if mine is None:  # not embedded: nothing to compare
            continue
        if not isinstance(mine, dict) or not isinstance(theirs, dict):
            out.append(f"{section}: {'the run config has no such section' if theirs is None else 'not an object'}")
            continue
        first, second = _comparable(cls, section, mine), _comparable(cls, section, theirs)
        out += [f"{section}.{key} {_shown(first.get(key))} vs {_shown(second.get(key))}"
                for key in sorted(set(first) | set(second)) if first.get(key) != second.get(key)]
        if section == "data":
            a, b = mine.get("path"), theirs.get("path")
            if (isinstance(a, str) and isinstance(b, str) and not same_place(a, b) and Path(a).exists()
                    and Path(b).exists()):
                out.append(f"data.path {a} vs {b}")
    return out


def _comparable(cls: type, section: str, values: dict[str, Any]) -> dict[str, Any]:
    """A saved config section as plain values, with what `config_differences` does not compare left out."""
    values = {k: v for k, v in values.items() if k != "path" and f"{section}.{k}" not in EXECUTION_OPTIONS}
    try:
        read = dataclasses.asdict(from_saved(cls, values, section))
    except (ConfigError, TypeError, ValueError):  # a damaged section: compared as it is written
        read = values
    plain: dict[str, Any] = json.loads(json.dumps(read, default=str))
    return {k: v for k, v in plain.items() if k != "path" and f"{section}.{k}" not in EXECUTION_OPTIONS}


def _shown(value: Any) -> str:
    text = json.dumps(value, default=str)
    return text if len(text) <= 40 else text[:37] + "..."


def _run_execution(run_dir: Path) -> tuple[int, str]:
    """How the run rendered when it trained: its `train.threads` (0: none saved, or the machine's default) and its
    `train.backend` ('auto' when none is saved)."""
    train = (Run(run_dir).read_config(strict=False) or {}).get("train") or {}
    threads, backend = train.get("threads"), train.get("backend")
    return (threads if isinstance(threads, int) and not isinstance(threads, bool) and threads > 0 else 0,
            backend if isinstance(backend, str) and backend in BACKENDS else "auto")


def _score_model(model: Any, dataset: Dataset, *, lpips_net: str | None, warmup: int, measure_fps: bool,
                 backend: str = "auto") -> EvalResult:
    """`evaluate` of a model on its dataset's test views, on the background and with the rasterizer backend the
    trainer rendered with."""
    background = torch.tensor(dataset.background, dtype=torch.float32)
    result = evaluate(lambda cam: model.render(cam, t=float(cam.time), background=background, backend=backend),
                      dataset.test, dataset.load_image, lpips_net=lpips_net, warmup=warmup)
    if not measure_fps:
        result.speed = None
    return result


def _other_data(run_dir: Path, data_path: str | Path | None, bitstream: Path | None = None,
                config_dir: Path | None = None) -> str | None:
    """The name evaluations on `data_path` are filed under: None for the run's own data (where its config points:
    for a `.stgc`, the run config it embeds, as `open_run_dataset` reads it; else `config_dir`'s, by default
    `run_dir`'s)."""
    if data_path is None:
        return None
    if bitstream is None:
        embedded = None
    elif is_video_stgc(bitstream):  # each segment embeds its run's config; they share the video's data
        embedded = embedded_data_section(read_video_segment_metadata(bitstream, 0))
    else:
        embedded = embedded_data_section(read_stgc_metadata(bitstream))
    if embedded is not None:
        saved_path = embedded.get("path")
    else:
        saved = saved_run_data(config_dir or run_dir)
        saved_path = saved[1] if saved is not None else None
    if saved_path is not None and same_place(data_path, saved_path):
        return None
    other = Path(data_path).resolve()
    # Two datasets with one folder name must not share (and overwrite) one record: the second gets its path's hash.
    earlier = read_json_object(Run(run_dir).eval_paths(other.name, bitstream)[0], strict=False)
    if earlier is not None and earlier.get("data") and not same_place(earlier["data"], other):
        return f"{other.name}-{hashlib.sha256(str(other).encode()).hexdigest()[:8]}"
    return other.name


def _evaluate_video_bitstream(target: Path, data_path: str | Path | None, *, lpips_net: str | None, warmup: int,
                              measure_fps: bool) -> dict[str, Any]:
    """`evaluate_run` of a whole-video .stgc: every segment on its own frames, then the whole video as
    `video_record` sums it, sized by the container file (its index included); eval_<stem>.json with per-view rows
    of all segments in eval_<stem>_per_view.csv, and the seam figure seams_<stem>.png beside the file."""
    records, curves, rows = [], [], []
    threads, backend = _run_execution(target.parent)  # the video's folder holds its run's config
    for segment in video_bitstream_segments(target, data_path):
        with machine.threads(threads):
            result = _score_model(segment.model, segment.dataset, lpips_net=lpips_net, warmup=warmup,
                                  measure_fps=measure_fps, backend=backend)
        summary = segment.run.read_summary(strict=False) if segment.run else None
        records.append((segment.name, eval_record(result, segment.size, {"train_seconds": training_seconds(summary),
                                                                         **dataset_identity(segment.dataset)})))
        curves.append((segment.name, [(v.frame, v.psnr) for v in result.views]))
        rows += [(segment.name, v) for v in result.views]
    record = aggregate_video_records(records)
    index = read_video_index(target)
    record.update({"size_bytes": index.file_bytes, "size_mb": index.file_bytes / 2**20,
                   "mbps": index.file_bytes * 8 / record["duration_s"] / 1e6 if record["duration_s"] else None,
                   "container_overhead_bytes": index.overhead_bytes, "target": str(target),
                   "bitstream": target.name, "bitstream_sha256": file_sha256(target),
                   "data": str(Path(data_path).resolve()) if data_path is not None else record.get("data")})
    foreign = foreign_video(target, index)
    if foreign is not None:  # as for a single model's file (`write_eval`)
        log.warning("%s holds another video than the run in %s (%s): its record says so, and reports leave it out "
                    "of this run's points", target, target.parent, foreign)
        record.update(foreign=foreign, train_seconds=None)
    seams = [seam_of(name, curve) for name, curve in curves]
    record["seams"] = [{k: v for k, v in seam.items() if k != "frames"} for seam in seams if seam]
    other = _other_data(target.parent, data_path, target)
    json_path, csv_path = Run(target.parent).eval_paths(other, target)
    write_json(json_path, record)
    _write_per_view(csv_path, rows)
    if record["seams"]:
        seams_name = f"seams_{target.stem}" + (f"_on_{other}" if other else "")
        seam_plot([seam for seam in seams if seam], target.parent / f"{seams_name}.png")
    return record


def foreign_video(path: Path, index: Any) -> str | None:
    """Why a whole-video .stgc (its `index`, `read_video_index`) is not the video of the run in its folder, or None
    where it is or the folder holds no run: `foreign_model` for each segment against the folder's segment of the
    same frames, whatever data the evaluation is given."""
    beside = Run(path.parent)
    if not beside.is_video():
        if beside.has_config() or (beside.path / Run.RESTORED_FROM).is_file():
            return "a whole video's file in the folder of a single model's run"
        return None
    plan = beside.read_video()["segments"]
    frames = [(e.first_frame, e.num_frames) for e in index.entries]
    if [(int(s["start"]), int(s["duration"])) for s in plan] != frames:
        return f"its segments cover frames {frames}, the video's {[(s['start'], s['duration']) for s in plan]}"
    for k, segment in enumerate(plan):
        why = foreign_model(Run(beside.path / str(segment["name"])), read_video_segment_metadata(path, k, index))
        if why is not None:
            return f"segment {k}: {why}"
    return None


# Per-view means that a whole video averages over all its views (each segment's weighted by its number of views).
_VIEW_MEANS = ("psnr", "ssim", "lpips", *YUV_KEYS)


def _weighted(records: Sequence[Mapping[str, Any]], key: str, weight: str = "num_views") -> float | None:
    pairs = [(float(r[key]), float(r.get(weight) or r.get("views") or 0)) for r in records if r.get(key) is not None]
    total = sum(w for _, w in pairs)
    return sum(v * w for v, w in pairs) / total if total > 0 else None


def _renders_per_second(records: Sequence[Mapping[str, Any]]) -> float | None:
    """The whole's FPS: all timed renders over all their time, i.e. the harmonic mean of the parts' FPS weighted by
    the renders each timed (`render_speed.frames_timed`, else its views); the arithmetic mean would overstate it."""
    def timed(r: Mapping[str, Any]) -> float:
        return float((r.get("render_speed") or {}).get("frames_timed") or r.get("num_views") or 0)

    pairs = [(float(r["fps"]), timed(r)) for r in records if r.get("fps")]
    seconds = sum(w / v for v, w in pairs)
    return sum(w for _, w in pairs) / seconds if seconds > 0 else None


def video_record(run_dir: str | Path, other_data: str | None = None) -> dict[str, Any]:
    """The whole video's evaluation from its segments' own records (RUN/segment_<k>/eval.json, or their records on
    `other_data`): PSNR, SSIM and YUV-PSNR over all test views x all frames, total Gaussians and bytes, Mbps over
    the whole duration, and a row per segment and per camera."""
    run = Run(run_dir)
    records = []
    for segment in run.segments():
        record = segment.read_eval(other_data)
        if record is None:
            raise DataError(segment.path, "segment has no evaluation yet (stgc eval the video run)")
        records.append((segment.path.name, record))
    if not records:
        raise DataError(run.path, "whole-video run without segments")
    return aggregate_video_records(records)


def aggregate_video_records(records: Sequence[tuple[str, Mapping[str, Any]]]) -> dict[str, Any]:
    """The whole video's record from its segments' (name, eval record) in time order (see `video_record`)."""
    rows = [r for _, r in records]
    duration = sum(float(r.get("duration_s") or 0.0) for r in rows)
    size_bytes = sum(int(r.get("size_bytes") or 0) for r in rows)
    video: dict[str, Any] = {key: _finite(_weighted(rows, key)) for key in _VIEW_MEANS}
    video.update({
        "num_gaussians": sum(int(r.get("num_gaussians") or 0) for r in rows),
        "size_bytes": size_bytes,
        "size_mb": size_bytes / 2**20,
        "duration_s": duration,
        "mbps": size_bytes * 8 / duration / 1e6 if duration > 0 else None,
        "fps": _renders_per_second(rows),
        "num_views": sum(int(r.get("num_views") or 0) for r in rows),
        "segments": len(rows),
        # unknown for the whole when unknown for a part (a container away from its runs): not 0 s
        "train_seconds": None if any(r.get("train_seconds") is None for r in rows) else
        sum(float(r["train_seconds"]) for r in rows),
        "per_segment": {name: {"frames": [min(r.get("frames") or [0]), max(r.get("frames") or [0])],
                               "views": r.get("num_views"), "psnr": r.get("psnr"), "ssim": r.get("ssim"),
                               "psnr_yuv": r.get("psnr_yuv"), "num_gaussians": r.get("num_gaussians"),
                               "size_mb": r.get("size_mb"), "mbps": r.get("mbps")} for name, r in records},
    })
    cameras = sorted({c for r in rows for c in (r.get("per_camera") or {})})
    # The test set, as a single model's record names it: reports compare only records of one test set.
    video["cameras"] = sorted({str(c) for r in rows for c in (r.get("cameras") or [])}) or cameras
    video["frames"] = sorted({int(f) for r in rows for f in (r.get("frames") or [])})
    for key in ("data", "downscale", "video_fps"):
        values = {json.dumps(r.get(key)) for r in rows}
        video[key] = rows[0].get(key) if len(values) == 1 else None  # segments on different data: unknown
    video["per_camera"] = {c: {key: _finite(_weighted([r["per_camera"][c] for r in rows
                                                       if c in (r.get("per_camera") or {})],
                                                      key, "views")) for key in _VIEW_MEANS}
                           | {"views": sum(int(r["per_camera"][c].get("views") or 0) for r in rows
                                           if c in (r.get("per_camera") or {}))} for c in cameras}
    video["units"] = rows[0].get("units")
    return video


SEAMS_PNG = "seams.png"


def segment_seams(run_dir: str | Path, other_data: str | None = None) -> list[dict[str, Any]]:
    """Per segment: test PSNR (mean over the test cameras) at its first, middle and last frames, and the seam
    loss: the middle's PSNR minus the mean of the two ends (what a viewer sees as a jump at every boundary); with
    `frames`: [(frame, PSNR)] for every frame. From the segments' RUN/segment_<k>/eval_per_view.csv (or their
    per-view files on `other_data`)."""
    seams = []
    for segment in Run(run_dir).segments():
        per_view = segment.eval_paths(other_data)[1]
        if not per_view.is_file():
            raise DataError(segment.path, "segment has no per-view evaluation yet (stgc eval the video run)")
        with per_view.open(newline="") as f:
            views = [(int(row["frame"]), float(row["psnr"])) for row in csv.DictReader(f)
                     if row.get("psnr") not in (None, "")]
        seam = seam_of(segment.path.name, views)
        if seam:
            seams.append(seam)
    return seams


def seam_of(name: str, views: Sequence[tuple[int, float]]) -> dict[str, Any] | None:
    """A segment's seam record (see `segment_seams`) from its test views' (frame, PSNR); None without views."""
    by_frame: dict[int, list[float]] = {}
    for frame, value in views:
        if value is not None and not math.isnan(value):  # an exact view counts at the ceiling, as in the means
            by_frame.setdefault(int(frame), []).append(min(float(value), PSNR_CEILING_DB))
    if not by_frame:
        return None
    frames = sorted(by_frame)
    curve = [(frame, float(np.mean(by_frame[frame]))) for frame in frames]
    first, middle, last = curve[0][1], curve[len(curve) // 2][1], curve[-1][1]
    return {"segment": name, "first_frame": frames[0], "last_frame": frames[-1], "psnr_first": first,
            "psnr_middle": middle, "psnr_last": last, "seam_loss_db": middle - (first + last) / 2, "frames": curve}


def seam_plot(seams: Sequence[Mapping[str, Any]], png: Path) -> None:
    """Test PSNR over the whole video's frames, one line per segment, boundaries marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 3.6), dpi=100)
    for seam in seams:
        frames, values = zip(*seam["frames"])
        ax.plot(frames, values, marker="o", markersize=3, linewidth=1.4, label=seam["segment"])
        ax.axvline(seam["first_frame"] - 0.5, color="grey", linewidth=0.8, linestyle=":")
    ax.set_xlabel("frame")
    ax.set_ylabel("test PSNR (dB), mean over cameras")
    ax.set_title("PSNR across segment boundaries (dotted)", fontsize=11)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    with atomic_path(png) as tmp:
        fig.savefig(tmp, format="png", dpi=150)
    plt.close(fig)


def write_video_eval(run_dir: str | Path, other_data: str | None = None, data: Path | None = None) -> dict[str, Any]:
    """Write the whole video's record (`video_record`, with its `seams`) as RUN/eval.json and the seam figure as
    RUN/seams.png (on `other_data`: RUN/eval_on_<name>.json and RUN/seams_on_<name>.png, the record naming the
    `data` folder, which the next evaluation on a folder of the same name tells apart), and return the record."""
    record = video_record(run_dir, other_data)
    seams = segment_seams(run_dir, other_data)
    record["seams"] = [{k: v for k, v in seam.items() if k != "frames"} for seam in seams]
    if other_data is not None:
        record["other_data"] = other_data
        if data is not None:
            record["data"] = str(data)
    if seams:
        png = Path(run_dir) / SEAMS_PNG
        seam_plot(seams, png if other_data is None else png.with_name(f"{png.stem}_on_{other_data}.png"))
    write_json(Run(run_dir).eval_paths(other_data)[0], record)
    return record


def _default_model_loader(target: Path) -> Any:
    if target.suffix == ".stgc":

        return load_model(target)

    return STGModel.load(target)
