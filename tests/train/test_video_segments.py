"""Whole videos as segments (`stgc train --segment-frames N`): layout, resume, and the whole video's evaluation."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import shutil
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
from scenes import write_panoptic_scene

from stgc.cli import main
from stgc.codec import load_video_segment, read_video_index
from stgc.compaction import CompactionConfig
from stgc.eval.video import _camera_at as camera_at
from stgc.eval.video import load_model_and_dataset, render_image
from stgc.run import Run
from stgc.train.video import plan_segments

QUICK = ["--set", "train.iterations=4", "--set", "train.schedule_scale=1", "--set", "data.init_source=random",
         "--set", "data.max_points_per_frame=200", "--set", "train.progress=false", "--set", "train.tensorboard=false",
         "--set", "train.save_iterations=[4]", "--set", "train.checkpoint_every=2",
         "--no-ray"]  # segments as tasks on Ray: tests/test_distributed.py


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_panoptic_scene(tmp_path_factory.mktemp("video"), views=5, frames=5, width=32, height=24)


def test_segments_are_consecutive_and_a_short_tail_is_its_own_segment():
    assert [(s["start"], s["duration"]) for s in plan_segments([0, 1, 2, 3, 4], 2)] == [(0, 2), (2, 2), (4, 1)]
    assert [s["name"] for s in plan_segments(list(range(10, 16)), 3)] == ["segment_000", "segment_001"]
    assert [(s["start"], s["duration"]) for s in plan_segments(list(range(10, 16)), 3)] == [(10, 3), (13, 3)]


def test_a_video_trains_as_segment_runs_and_evaluates_as_one(scene, tmp_path, capsys):
    out = tmp_path / "video"
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "2", *QUICK]) == 0
    run = Run(out)
    assert run.is_video() and [s.path.name for s in run.segments()] == ["segment_000", "segment_001", "segment_002"]
    windows = []
    for segment in run.segments():
        config = segment.read_config()
        windows.append((config["data"]["start"], config["data"]["duration"]))
        assert segment.training_finished() and segment.latest_model_dir() is not None
    assert windows == [(0, 2), (2, 2), (4, 1)]
    # Each segment's own messages are in its task log (on Ray the driver does not show a worker's console).
    assert "random points" in (out / "segment_002" / "task.log").read_text()
    record = json.loads((out / "eval.json").read_text())
    segments = [s.read_eval() for s in run.segments()]
    assert record["segments"] == 3 and record["num_views"] == sum(s["num_views"] for s in segments) == 5
    assert record["num_gaussians"] == sum(s["num_gaussians"] for s in segments)
    # Over all test views x frames: each segment's mean weighted by its views.
    expected = sum(s["psnr"] * s["num_views"] for s in segments) / 5
    assert record["psnr"] == pytest.approx(expected)
    assert record["mbps"] == pytest.approx(record["size_bytes"] * 8 / record["duration_s"] / 1e6)
    assert "segment_002" in capsys.readouterr().out
    # Named with --data: its own data is its own evaluation; the same frames elsewhere (the data moved) are filed
    # as evaluations on that data, video and segments alike (refused: "evaluated on its own data").
    assert main(["eval", str(out), "--data", str(scene.root), "--no-fps"]) == 0
    assert sorted(p.name for p in out.glob("eval*.json")) == ["eval.json"]
    moved = tmp_path / "moved"
    shutil.copytree(scene.root, moved)
    assert main(["eval", str(out), "--data", str(moved), "--no-fps"]) == 0
    elsewhere = json.loads((out / "eval_on_moved.json").read_text())
    assert elsewhere["psnr"] == pytest.approx(record["psnr"]) and elsewhere["other_data"] == "moved"
    assert all((s.path / "eval_on_moved.json").is_file() for s in run.segments())
    assert json.loads((out / "eval.json").read_text())["psnr"] == record["psnr"]
    # The seams: each segment's first / middle / last frame PSNR (mean over test cameras), and the figure.
    assert [(s["segment"], s["first_frame"], s["last_frame"]) for s in record["seams"]] == [
        ("segment_000", 0, 1), ("segment_001", 2, 3), ("segment_002", 4, 4)]
    with open(out / "segment_001" / "eval_per_view.csv") as f:
        rows = [r for r in csv.DictReader(f)]
    at_3 = [float(r["psnr"]) for r in rows if r["frame"] == "3"]
    seam = record["seams"][1]
    assert seam["psnr_last"] == pytest.approx(sum(at_3) / len(at_3))
    assert seam["seam_loss_db"] == pytest.approx(seam["psnr_middle"] - (seam["psnr_first"] + seam["psnr_last"]) / 2)
    assert (out / "seams.png").stat().st_size > 1000
    # `stgc eval` on the video re-evaluates every segment and writes the same whole-video record.
    assert main(["eval", str(out), "--no-fps"]) == 0
    again = json.loads((out / "eval.json").read_text())
    assert again["psnr"] == pytest.approx(record["psnr"]) and again["num_gaussians"] == record["num_gaussians"]


def test_resume_trains_only_what_is_unfinished(scene, tmp_path, capsys):
    out = tmp_path / "video"
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "3", *QUICK]) == 0
    run = Run(out)
    first, second = run.segments()
    kept = (first.summary_path.stat().st_mtime_ns, (first.latest_model_dir() / "point_cloud.ply").read_bytes())
    # The second segment "was killed": its summary is gone, its checkpoint and saved model stay.
    second.summary_path.unlink()
    # Its saved model is not the video's: compress refuses to pack it (it used to, silently).
    assert main(["compress", str(out), "--out", str(out / "v.stgc"), "--set", "codec.allocation=ladder"]) == 2
    assert "segment_001" in capsys.readouterr().err and not (out / "v.stgc").exists()
    # Nor is it scored as the video (it was: its half-trained model went into the video's PSNR and rate).
    video_record = (out / "eval.json").read_bytes()
    assert main(["eval", str(out)]) == 2
    assert "segment_001: segment has not finished training" in capsys.readouterr().err
    assert (out / "eval.json").read_bytes() == video_record
    assert main(["train", "--out", str(out), "--resume", "--no-ray"]) == 0
    assert second.training_finished()
    assert (first.summary_path.stat().st_mtime_ns, (first.latest_model_dir() / "point_cloud.ply").read_bytes()) == kept
    # A resumed video keeps its segments.
    capsys.readouterr()
    assert main(["train", "--out", str(out), "--resume", "--segment-frames", "2"]) == 2
    assert "cut into 3-frame segments; a resumed run keeps them" in capsys.readouterr().err


def test_a_new_video_refuses_an_existing_run_unless_overwritten(scene, tmp_path, capsys):
    out = tmp_path / "video"
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "5", *QUICK]) == 0
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "5", *QUICK]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "2", "--overwrite", *QUICK]) == 0
    assert len(Run(out).segments()) == 3


def test_a_segment_on_bad_data_fails_the_command_by_name_and_the_others_are_kept(tmp_path, capsys):
    scene = write_panoptic_scene(tmp_path / "scene", views=5, frames=4, width=32, height=24)
    # A training view of frame 3, cut short: its header reads (opening the data checks every header), its pixels do
    # not, so the failure comes from the segment that trains on it.
    image = scene.root / "ims" / "1" / "000003.png"
    image.write_bytes(image.read_bytes()[:200])
    out = tmp_path / "video"
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "2", *QUICK]) == 2
    err = capsys.readouterr().err
    assert "segment_001" in err and "000003.png" in err and "segment_000" not in err.split("failed")[-1]
    first, second = Run(out).segments()
    assert first.training_finished() and not second.training_finished()


def test_a_video_renders_across_its_segments(scene, tmp_path):
    from stgc.model import STGModel

    out = tmp_path / "video"
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "2", *QUICK]) == 0
    # The scene is static and the segments nearly alike (52 dB apart): segment_002's model is made invisible, so
    # that a frame drawn by the wrong segment shows.
    last = Run(out / "segment_002").latest_model_dir()
    hidden = STGModel.load(last)
    hidden.params["opacity"].data.fill_(-30.0)
    hidden.save(last)
    assert main(["render", str(out), "--camera", "0", "--out", str(tmp_path / "all.mp4")]) == 0
    frames = imageio.mimread(tmp_path / "all.mp4")
    assert len(frames) == 5  # frames 0-4 from segments 0, 0, 1, 1, 2
    # Only segment_002's frame is the bare background.
    assert np.asarray(frames[4], float).std() < 2 < np.asarray(frames[3], float).std()
    # Frame 4 is segment_002's, frame 1 segment_000's: each as its own segment renders it (up to the video coding).
    for frame, segment in ((4, "segment_002"), (1, "segment_000")):
        model, dataset = load_model_and_dataset(out / segment)
        still = render_image(model, camera_at(dataset, "0", frame), None, (0.0, 0.0, 0.0)).astype(float)
        mse = np.mean((frames[frame][..., :3].astype(float) - still) ** 2)
        assert 10 * np.log10(255**2 / max(mse, 1e-9)) > 30, (frame, mse)
    assert main(["render", str(out), "--orbit", "--out", str(tmp_path / "orbit.mp4")]) == 2


def test_a_whole_video_is_one_bitstream_that_evaluates_renders_and_restores(scene, tmp_path, capsys):
    out = tmp_path / "video"
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "2", *QUICK]) == 0
    bitstream = out / "video.stgc"
    assert main(["compress", str(out), "--out", str(bitstream), "--set", "codec.allocation=ladder"]) == 0
    index = read_video_index(bitstream)
    assert [(e.first_frame, e.num_frames) for e in index.entries] == [(0, 2), (2, 2), (4, 1)]
    # Each segment's bytes are exactly what compressing that segment alone writes.
    for k, segment in enumerate(Run(out).segments()):
        alone = tmp_path / f"alone_{k}.stgc"
        assert main(["compress", str(segment.path), "--out", str(alone), "--set", "codec.allocation=ladder"]) == 0
        entry = index.entries[k]
        assert bitstream.read_bytes()[entry.offset: entry.offset + entry.length] == alone.read_bytes()

    # eval: per segment on its own frames, whole video sized by the container file.
    assert main(["eval", str(bitstream), "--no-fps"]) == 0
    record = json.loads((out / "eval_video.json").read_text())
    assert record["segments"] == 3 and record["num_views"] == 5
    assert record["size_bytes"] == bitstream.stat().st_size
    assert record["mbps"] == pytest.approx(record["size_bytes"] * 8 / record["duration_s"] / 1e6)
    assert record["container_overhead_bytes"] == 32 + 3 * 32
    assert sum(s["size_mb"] for s in record["per_segment"].values()) * 2**20 == pytest.approx(
        record["size_bytes"] - record["container_overhead_bytes"])
    # Independently: segment 1's PSNR is what its decoded model scores on its own run's dataset.
    model, _ = load_video_segment(bitstream, 1)
    _, dataset = load_model_and_dataset(out / "segment_001")
    scores = []
    for cam in dataset.test:
        image = render_image(model, cam, None, (0.0, 0.0, 0.0)).astype(float) / 255.0
        truth = np.asarray(dataset.load_image(cam))[..., :3].astype(float) / 255.0
        scores.append(10 * np.log10(1.0 / np.mean((image - truth) ** 2)))
    assert record["per_segment"]["segment_001"]["psnr"] == pytest.approx(np.mean(scores), abs=0.05)
    with open(out / "eval_video_per_view.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["segment"] for r in rows].count("segment_002") == 1 and len(rows) == 5
    assert [s["segment"] for s in record["seams"]] == ["segment_000", "segment_001", "segment_002"]
    assert (out / "seams_video.png").stat().st_size > 1000
    # Named with --data, the video's own data files the record under its own name (a container embeds no run
    # config of its own: the folder's is the video's).
    assert main(["eval", str(bitstream), "--data", str(scene.root), "--no-fps"]) == 0
    assert sorted(p.name for p in out.glob("eval_video*.json")) == ["eval_video.json"]
    assert record["video_fps"] == 30.0  # the frame rate its Mbps assume, as a single model's record names it
    again = json.loads((out / "eval_video.json").read_text())
    # ... and its segments are still its runs' (their training time was wiped from the record).
    assert again["train_seconds"] == record["train_seconds"] > 0 and again["psnr"] == record["psnr"]

    # Away from its run: the configs the segments embed name the same data; the same numbers come out.
    away = tmp_path / "away"
    away.mkdir()
    shutil.copy(bitstream, away / "copy.stgc")
    assert main(["eval", str(away / "copy.stgc"), "--no-fps"]) == 0
    moved = json.loads((away / "eval_copy.json").read_text())
    assert moved["psnr"] == pytest.approx(record["psnr"]) and moved["size_bytes"] == record["size_bytes"]
    assert record["train_seconds"] > 0 and moved["train_seconds"] is None  # unknown away from its runs, not 0 s
    # Its own data named with --data is its own data there too (it was filed as other data, eval_copy_on_<name>).
    assert main(["eval", str(away / "copy.stgc"), "--data", str(scene.root), "--no-fps"]) == 0
    assert sorted(p.name for p in away.glob("eval_*.json")) == ["eval_copy.json"]

    # Copied into another video's folder (the same frames, other data): scored on its own data, as away from its
    # run; it was scored on that folder's data.
    other_scene = write_panoptic_scene(tmp_path / "other_scene", views=5, frames=5, width=32, height=24, seed=3)
    other = tmp_path / "other"
    assert main(["train", str(other_scene.root), "--out", str(other), "--segment-frames", "2", *QUICK]) == 0
    shutil.copy(bitstream, other / "copy.stgc")
    assert main(["eval", str(other / "copy.stgc"), "--no-fps"]) == 0
    beside = json.loads((other / "eval_copy.json").read_text())
    assert beside["psnr"] == pytest.approx(record["psnr"]) and beside["train_seconds"] is None

    # render plays across the segments of the file.
    assert main(["render", str(bitstream), "--camera", "0", "--out", str(tmp_path / "all.mp4")]) == 0
    assert len(imageio.mimread(tmp_path / "all.mp4")) == 5
    assert main(["render", str(bitstream), "--out", str(tmp_path / "still.png")]) == 2  # a still has no segment
    assert main(["export", str(out), "--out", str(tmp_path / "frames")]) == 2  # nor an export of the whole run
    assert "each segment is its own model" in capsys.readouterr().err

    # decompress restores a whole-video run, which evaluates to the bitstream's numbers.
    restored = tmp_path / "restored"
    assert main(["decompress", str(bitstream), "--out", str(restored)]) == 0
    assert [(s["start"], s["duration"]) for s in Run(restored).read_video()["segments"]] == [(0, 2), (2, 2), (4, 1)]
    assert main(["eval", str(restored), "--no-fps"]) == 0
    again = json.loads((restored / "eval.json").read_text())
    assert again["psnr"] == pytest.approx(record["psnr"], abs=1e-3)
    assert again["num_gaussians"] == record["num_gaussians"]
    # A restored segment's model is its final one: its record says so (a report named it half-trained).
    assert json.loads((restored / "segment_000" / "eval.json").read_text())["training_finished"] is True
    # Its segments hold final models though no training summary says so: compress packs them again (it refused
    # them as unfinished, with a resume that could not run).
    assert main(["compress", str(restored), "--out", str(restored / "again.stgc"), "--set", "codec.allocation=ladder"]) == 0

    # A single-model reader refuses the container by name; a damaged container fails before anything is written.
    damaged = tmp_path / "damaged.stgc"
    data = bytearray(bitstream.read_bytes())
    data[index.entries[2].offset + 40] ^= 0xFF
    damaged.write_bytes(bytes(data))
    assert main(["decompress", str(damaged), "--out", str(tmp_path / "nothing")]) == 2
    assert not (tmp_path / "nothing").exists()


def test_segment_tasks_get_absolute_paths_whatever_the_user_typed(scene, tmp_path, monkeypatch):
    # A Ray worker on another node reads a relative path against its own working directory.
    import stgc.train.video as video
    from stgc.options import resolve_configs

    tasks = []
    monkeypatch.setattr(video, "run_tasks", lambda given, **kw: tasks.extend(given))
    monkeypatch.chdir(scene.root.parent)
    video.train_video(scene.root.name, resolve_configs("cpu", {}, {}, {}), "runs/vid", segment_frames=1)
    assert tasks and all(Path(t.args[0]).is_absolute() and Path(t.args[2]).is_absolute() for t in tasks)
    assert Path(tasks[0].args[2]) == scene.root.parent / "runs" / "vid" / "segment_000"


def test_a_video_whose_start_was_killed_before_saving_its_options_is_not_resumed_with_others(scene, tmp_path, capsys):
    run = tmp_path / "vid"
    run.mkdir()
    Run(run).write_video({"segment_frames": 1, "data_path": str(scene.root), "segments": plan_segments([0, 1], 1)})
    assert main(["train", str(scene.root), "--out", str(run), "--resume"]) == 2
    assert "before it saved its options" in capsys.readouterr().err
    assert not (run / "segment_000").exists()


def test_segments_without_test_views_and_contradicting_ray_options_are_refused_before_anything_is_written(
        scene, tmp_path, capsys, monkeypatch):
    """Monocular data holds out images at a few times: a segment without one trained to its end, then failed its
    evaluation (and stopped the segments after it), leaving a video nothing could evaluate. --no-ray with
    --ray-address was refused after the run folder was written (a second start then found 'a run')."""
    from PIL import Image

    from stgc.data.cameras import w2c_to_opengl_c2w

    mono = tmp_path / "mono"
    times = {"train": [0.0, 0.25, 0.5, 0.75, 1.0], "test": [0.1]}
    for split, ts in times.items():
        frames = []
        for i, t in enumerate(ts):
            (mono / split).mkdir(parents=True, exist_ok=True)
            Image.fromarray(np.full((12, 16, 3), 60 * i, np.uint8)).save(mono / split / f"r_{i:03d}.png")
            w2c = np.eye(4)
            w2c[:3, 3] = [0, 0, 3]
            frames.append({"file_path": f"./{split}/r_{i:03d}", "time": t,
                           "transform_matrix": w2c_to_opengl_c2w(w2c).tolist()})
        (mono / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
    out = tmp_path / "video"
    assert main(["train", str(mono), "--out", str(out), "--segment-frames", "2", *QUICK]) == 2
    assert "segment_001, segment_002 would have no test view" in capsys.readouterr().err and not out.exists()
    # Without evaluation nothing needs them: the segments are trained (here by a stand-in) as before.
    import stgc.train.video

    trained = []
    monkeypatch.setattr(stgc.train.video, "train_segment", lambda *args: trained.append(args[2]) or {})
    assert main(["train", str(mono), "--out", str(out), "--segment-frames", "2", *QUICK,
                 "--set", "train.eval_at_end=false", "--set", "train.eval_every=0"]) == 0
    assert [Path(p).name for p in trained] == ["segment_000", "segment_001", "segment_002"]
    shutil.rmtree(out)
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "2", *QUICK,
                 "--ray-address", "127.0.0.1:1"]) == 2
    assert "--no-ray asks for none" in capsys.readouterr().err and not out.exists()


def test_a_segment_that_raises_anything_fails_alone_and_the_others_still_run(tmp_path):
    """In this process as on Ray: an error that is not the data's (a bug) stopped every segment after it."""
    from stgc.distributed import Task, TasksFailed, run_tasks

    def work(x: int) -> int:
        if x == 1:
            raise ZeroDivisionError("a bug")
        return x

    tasks = [Task(name=f"t{k}", function=work, args=(k,)) for k in range(3)]
    done = []
    with pytest.raises(TasksFailed, match="ZeroDivisionError: a bug"):
        run_tasks(tasks, on_done=lambda i, r: done.append(r))
    assert done == [0, 2]


def test_a_video_evaluated_on_two_datasets_of_one_folder_name_keeps_each_one_s_scores(scene, tmp_path, capsys):
    """Each segment filed the second dataset under a name of its own (its earlier record named the first), while
    the video combined the records filed under the plain name: the first dataset's scores, printed and saved as the
    second's. Also: the video's duration is its five frames' (Mbps follows it)."""
    from stgc.data import open_dataset

    out = tmp_path / "video"
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "2", *QUICK]) == 0
    own = json.loads((out / "eval.json").read_text())
    assert own["duration_s"] == pytest.approx(5 / open_dataset(scene.root).fps)
    first, second = tmp_path / "d1" / "moved", tmp_path / "d2" / "moved"
    shutil.copytree(scene.root, first)
    shutil.copytree(scene.root, second)
    for image_file in (second / "ims").rglob("*.*"):
        image = imageio.imread(image_file)
        imageio.imwrite(image_file, (image // 2).astype(image.dtype))
    scores = {}
    for data in (first, second):
        assert main(["eval", str(out), "--data", str(data), "--no-fps"]) == 0
        records = sorted(out.glob("eval_on_moved*.json"))
        scores[data] = {json.loads(p.read_text())["data"]: json.loads(p.read_text())["psnr"] for p in records}
    after = scores[second]
    assert set(after) == {str(first.resolve()), str(second.resolve())}
    assert after[str(first.resolve())] > after[str(second.resolve())] + 1  # the darkened copy scores lower
    capsys.readouterr()


def test_a_video_restored_from_a_file_without_its_run_config_keeps_each_segment_s_frames(scene, tmp_path, capsys):
    """Restored without an embedded run config, each segment opened the data with every frame of the video: scored
    on all five frames (three times the views), its times scaled by the whole length, with a wrong duration."""
    from stgc.data import open_dataset

    out = tmp_path / "video"
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "2", *QUICK]) == 0
    bare = out / "bare.stgc"
    assert main(["compress", str(out), "--out", str(bare), "--set", "codec.embed_run_config=false"]) == 0
    assert main(["decompress", str(bare), "--out", str(tmp_path / "restored")]) == 0
    assert main(["eval", str(tmp_path / "restored"), "--data", str(scene.root), "--no-fps"]) == 0
    # No config names the data the restored video trained on: the given data is other data to it.
    record = json.loads((tmp_path / "restored" / f"eval_on_{scene.root.name}.json").read_text())
    assert record["num_views"] == 5
    assert record["duration_s"] == pytest.approx(5 / open_dataset(scene.root).fps)
    capsys.readouterr()


def test_a_video_stopped_early_says_so_and_resumes_to_its_evaluation(scene, tmp_path, capsys):
    """train.stop_after on a whole video printed "whole video written", then failed on segments without an
    evaluation with advice (stgc eval) that refuses unfinished segments."""
    out = tmp_path / "video"
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "2", *QUICK,
                 "--set", "train.stop_after=2"]) == 0
    said = capsys.readouterr().out
    assert "3 of 3 segments stopped before their end" in said and "--resume" in said
    assert not (out / "eval.json").exists()
    assert main(["train", "--out", str(out), "--resume", "--no-ray"]) == 0
    assert "whole video written" in capsys.readouterr().out
    assert json.loads((out / "eval.json").read_text())["segments"] == 3


def test_a_whole_video_loss_reference_gives_each_segment_its_own(scene, tmp_path, capsys):
    """Every segment was handed the video's reference folder, which holds no compaction log of its own: the run
    folder was written, then every segment failed. Segment k now compares with the reference's segment k, and a
    reference cut into other segments is refused before anything is written."""
    reference = tmp_path / "reference"
    quiet = ["--set", "train.eval_at_end=false"]
    assert main(["train", str(scene.root), "--out", str(reference), "--segment-frames", "3", *QUICK, *quiet,
                 "--set", "compaction.method=reference"]) == 0
    budget = ["--compaction", "st-knn", "--set", "compaction.loss_budget_db=0.5", "--set",
              "compaction.loss_signal=probe", "--set", f"compaction.loss_reference={reference}"]
    out = tmp_path / "pruned"
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "3", *QUICK, *quiet, *budget]) == 0
    for k, segment in enumerate(Run(out).segments()):
        assert segment.read_config()["compaction"]["loss_reference"] == str(reference.resolve() / f"segment_{k:03d}")
    other = tmp_path / "other"
    assert main(["train", str(scene.root), "--out", str(other), "--segment-frames", "2", *QUICK, *quiet,
                 *budget]) == 2
    assert "cut into other segments" in capsys.readouterr().err
    assert not other.exists()
    single = tmp_path / "single"
    assert main(["train", str(scene.root), "--out", str(single), *QUICK, *quiet,
                 "--set", "compaction.method=reference"]) == 0
    assert main(["train", str(scene.root), "--out", str(other), "--segment-frames", "3", *QUICK, *quiet,
                 *budget[:-1], f"compaction.loss_reference={single}"]) == 2
    assert "is a single run" in capsys.readouterr().err
    assert not other.exists()
    # A single run for a video of one segment is its reference, handed to the worker as an absolute path (a Ray
    # worker on another node reads a relative one against its own working directory).
    from stgc.train.video import _segment_loss_references

    relative = os.path.relpath(single)
    compaction = dataclasses.replace(CompactionConfig(), loss_reference=relative)
    plan = [{"name": "segment_000", "start": 0, "duration": 3}]
    assert _segment_loss_references({"compaction": compaction}, plan) == [str(single.resolve())]
