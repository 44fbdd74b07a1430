"""Whole videos as consecutive segments: STG trains a 300-frame video as six 50-frame models, and so does
`stgc train DATA --out RUN --segment-frames N`.

The frames the data options select (all of them, or `data.start`/`data.duration`) are cut into consecutive
segments of N frames; the last one is shorter when N does not divide the count (it is trained as it is, with its
own initial points: STG would do the same, and merging it into its neighbour would give that segment a different
length from the others). RUN holds `config.json` (the options shared by every segment), `video.json` (the segments)
and one complete, resumable run per segment in RUN/segment_<k>/, whose own config.json differs only in
`data.start`/`data.duration`. Segments are independent: each is a task (`stgc.distributed`), trained in parallel on
Ray (local or a cluster) or one after another in this process; a task that is retried after its worker died, and
`--resume` after the driver died, continue each unfinished segment from its last checkpoint (a finished segment is
never redone).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

from stgc.data import DataConfig
from stgc.data.dataset import segments
from stgc.distributed import Task, check_ray_options, check_reachable, cpus_for_threads, run_tasks
from stgc.errors import StgcError
from stgc.run import Run
from stgc.train.config import TrainConfig
from stgc.train.loop import TestEvaluator, check_same_data, run_config, train

log = logging.getLogger(__name__)


def plan_segments(frames: list[int], segment_frames: int) -> list[dict[str, Any]]:
    """[{"name": "segment_<k>", "start", "duration"}] covering `frames` (consecutive) in order."""
    if segment_frames < 1:
        raise StgcError(f"--segment-frames must be at least 1, not {segment_frames}")
    if not frames:
        raise StgcError("the data selects no frames to cut into segments")
    return [{"name": f"segment_{k:03d}", "start": start, "duration": duration}
            for k, (start, duration) in enumerate(segments(len(frames), segment_frames, first=frames[0]))]


def train_video(data_path: str | Path, configs: dict[str, Any], out_dir: str | Path, segment_frames: int | None = None,
                *, resume: bool = False, overwrite: bool = False,
                evaluator: TestEvaluator | None = None, use_ray: bool = False,
                ray_address: str | None = None) -> list[dict[str, Any]]:
    """Train every segment of the video into RUN/segment_<k>/ (see the module docstring) as tasks
    (`stgc.distributed.run_tasks`: with use_ray, on a local Ray or the cluster at `ray_address`; else in order here);
    returns their training summaries in time order. resume: continue the video in `out_dir` (its saved segments;
    `segment_frames` must be None or the saved value); a finished segment is never trained again. evaluator: as
    `train`'s, for every segment."""
    check_ray_options(use_ray, ray_address)  # refused before anything is written
    if use_ray and ray_address is not None:
        check_reachable(ray_address)  # refused in seconds
    # Absolute: a worker on another node reads relative paths against its own working directory.
    data_path, out_dir = Path(data_path).resolve(), Path(out_dir).resolve()
    run = Run(out_dir)
    if resume and run.is_video():
        video = run.read_video()  # a video.json that is not the consecutive segments a start writes: named, refused
        _refuse_a_restored_video(run, video["segments"])
        if not run.has_config():
            raise StgcError(f"{run.path}: its start was killed before it saved its options (config.json), so resuming "
                            "would train its segments with other ones; start it again with --overwrite")
        if segment_frames is not None and int(segment_frames) != int(video["segment_frames"]):
            raise StgcError(f"{run.path}: the video was cut into {video['segment_frames']}-frame segments; a resumed "
                            "run keeps them")
        plan = video["segments"]
        run.check_segment_frames(plan)  # before any segment trains on frames other than its own
        # Before a segment not yet started trains on other data than the finished ones (`check_same_data`).
        check_same_data(run.read_config(strict=False), configs["data"].open(data_path), run.path)
        references = _segment_loss_references(configs, plan)
    else:
        if segment_frames is None:
            raise StgcError(f"{run.path}: not a whole-video run; give --segment-frames to start one")
        if resume and run.has_config():
            # Cutting it into segments would replace the single-segment run that --resume was asked to continue.
            raise StgcError(f"{run.path}: holds a single-segment run; --resume continues it as it was trained (drop "
                            "--segment-frames), or give a new --out for the whole video")
        data_cfg: DataConfig = configs["data"]
        whole = data_cfg.open(data_path)  # the frame window the data options select
        plan = plan_segments(list(whole.frames), int(segment_frames))
        if configs["train"].eval_at_end or configs["train"].eval_every:
            _refuse_segments_without_test_views(plan, whole, data_path)
        references = _segment_loss_references(configs, plan)  # refused before anything is written
        run = Run.create(out_dir, overwrite=overwrite)
        # video.json first: a start killed before config.json is still a video that --resume recognises.
        run.write_video({"segment_frames": int(segment_frames), "data_path": str(Path(data_path).resolve()),
                         "segments": plan})
        run.write_config(run_config(whole, configs, data_path=data_path))
    train_cfg: TrainConfig = configs["train"]
    tasks = []
    for index, segment in enumerate(plan):
        segment_run = Run(run.path / str(segment["name"]))
        if segment_run.training_finished():
            log.info("%s: finished already, kept", segment_run.path.name)
            continue
        log.info("segment %d of %d: frames %d-%d", index + 1, len(plan), segment["start"],
                 segment["start"] + segment["duration"] - 1)
        segment_configs = {**configs, "data": dataclasses.replace(
            configs["data"], start=int(segment["start"]), duration=int(segment["duration"]))}
        if references is not None:
            segment_configs["compaction"] = dataclasses.replace(configs["compaction"], loss_reference=references[index])
        tasks.append(Task(name=segment_run.path.name, function=train_segment,
                          args=(str(data_path), segment_configs, str(segment_run.path), evaluator),
                          num_cpus=cpus_for_threads(train_cfg.threads), progress=segment_run.progress,
                          log_file=segment_run.task_log_path))
    run_tasks(tasks, use_ray=use_ray, address=ray_address)
    return [segment_run.read_summary() or {} for segment_run in run.segments()]


def _refuse_a_restored_video(run: Run, plan: list[dict[str, Any]]) -> None:
    """`stgc decompress` of a whole-video file writes video.json and decoded segments, but no config.json of the
    video: told that its start was killed, a user gave --overwrite and lost the restored models."""
    if (run.path / Run.RESTORED_FROM).is_file() or any(
            (run.path / str(s["name"]) / Run.RESTORED_FROM).is_file() for s in plan):
        raise StgcError(f"{run.path}: holds a whole video restored from a bitstream (stgc decompress), not a "
                        "training: its segments hold decoded models without training options or checkpoints, so "
                        "there is nothing to resume; train the video into a new --out (--overwrite would remove the "
                        "restored models)")


def _segment_loss_references(configs: dict[str, Any], plan: list[dict[str, Any]]) -> list[str] | None:
    """Each segment's compaction.loss_reference when the video's names a whole-video reference run: its segment
    of the same frames (a video holds its logs per segment; every segment was handed the video's folder, and
    failed after the run folder was written), as absolute paths. None when there is no reference; a single run is
    the reference of a video of one segment (whose own check then says whether it fits), refused for more."""
    compaction = configs.get("compaction")
    reference = getattr(compaction, "loss_reference", None)
    if not reference:
        return None
    reference_run = Run(Path(reference))
    if not reference_run.is_video():
        if len(plan) > 1:  # one run's frames cannot be every segment's: each would fail after the folder is written
            raise StgcError(f"{reference_run.path}: compaction.loss_reference is a single run; a video of "
                            f"{len(plan)} segments compares each with the same segment of a reference video (train "
                            "it with compaction.method=reference and the same --segment-frames)")
        return [str(reference_run.path.resolve())]  # absolute, as the data and out paths: a worker's cwd differs
    segments = reference_run.read_video()["segments"]
    theirs = [(int(s["start"]), int(s["duration"])) for s in segments]
    mine = [(int(s["start"]), int(s["duration"])) for s in plan]
    if theirs != mine:
        raise StgcError(f"{reference_run.path}: compaction.loss_reference is a whole video cut into other segments "
                        f"(frames {theirs}, this video {mine}); train the reference with the same data window and "
                        "--segment-frames")
    return [str(reference_run.path.resolve() / str(s["name"])) for s in segments]


def _refuse_segments_without_test_views(plan: list[dict[str, Any]], whole: Any, data_path: Path) -> None:
    """Every segment of a run that evaluates is scored on its own test views: one without any (monocular data whose
    held-out images lie at a few times) would fail at its end, after its training, and leave the video
    unevaluable."""
    empty = [str(s["name"]) for s in plan
             if not any(whole.test_at(f) for f in range(int(s["start"]), int(s["start"]) + int(s["duration"])))]
    if empty:
        raise StgcError(f"{data_path}: segment(s) {', '.join(empty)} would have no test view (the held-out images "
                        "lie at other frames); choose longer segments (--segment-frames) or hold out views at every "
                        "frame (--data.test_cameras)")


def train_segment(data_path: str, configs: dict[str, Any], segment_dir: str,
                  evaluator: TestEvaluator | None) -> dict[str, Any]:
    """One segment's training, as a task (in this process or on a Ray worker): continues from the segment's last
    checkpoint when it has one, so a retried task redoes only the iterations since then."""
    data_cfg: DataConfig = configs["data"]
    dataset = data_cfg.open(data_path)
    dataset.verify_images(dataset.train)  # a corrupt image fails this segment now, named
    return train(dataset, data_cfg, configs["model"], configs["train"], configs["compaction"], segment_dir,
                 resume=True, evaluator=evaluator)

