"""A whole video's video.json is checked before a verb trusts it: its shape (integer frames, consecutive segments,
the names a training writes) and its agreement with what each segment recorded for itself; and a video restored
from a bitstream is named as such when asked to resume."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from scenes import write_panoptic_scene

from stgc.cli import main
from stgc.errors import DataError
from stgc.run import Run

QUICK = ["--set", "train.iterations=4", "--set", "train.schedule_scale=1", "--set", "data.init_source=random",
         "--set", "data.max_points_per_frame=200", "--set", "train.progress=false", "--set", "train.tensorboard=false",
         "--set", "train.save_iterations=[4]", "--set", "train.checkpoint_every=2", "--set", "train.eval_at_end=false",
         "--no-ray"]
LADDER = ["--set", "codec.allocation=ladder"]
PLAN = [{"name": "segment_000", "start": 0, "duration": 2}, {"name": "segment_001", "start": 2, "duration": 2},
        {"name": "segment_002", "start": 4, "duration": 1}]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A finished 5-frame video in 2-frame segments, and its scene: each test works on a copy."""
    scene = write_panoptic_scene(tmp_path_factory.mktemp("video_json"), views=5, frames=5, width=32, height=24)
    out = tmp_path_factory.mktemp("video_json_run") / "video"
    assert main(["train", str(scene.root), "--out", str(out), "--segment-frames", "2", *QUICK]) == 0
    return scene, out


def _copy(trained, tmp_path: Path) -> tuple[Path, Path]:
    scene, out = trained
    copy = tmp_path / "video"
    shutil.copytree(out, copy)
    return scene.root, copy


def _write_segments(video: Path, segments: list[dict]) -> None:
    """video.json with other segments (edited by hand), the rest as the training wrote it."""
    path = video / Run.VIDEO
    path.write_text(json.dumps({**json.loads(path.read_text()), "segments": segments}))


# Consecutive segments of integer frames, yet not the segments' own: segment_001 trained on frames 2-3, not 2.
SHIFTED = [PLAN[0], {**PLAN[1], "duration": 1}, {**PLAN[2], "start": 3, "duration": 2}]


@pytest.mark.parametrize("segments, message", [
    ([{**PLAN[0], "start": "0"}, *PLAN[1:]], "segment 0 (segment_000): start '0' is not a frame number"),
    ([PLAN[0], {**PLAN[1], "duration": "2"}, PLAN[2]], "segment 1 (segment_001): duration '2' is not a number"),
    ([PLAN[0], {**PLAN[1], "duration": 2.5}, PLAN[2]], "duration 2.5 is not a number of frames"),
    ([PLAN[0], {**PLAN[1], "duration": 2.0}, PLAN[2]], "duration 2.0 is not a number of frames"),
    ([{**PLAN[0], "duration": True}, *PLAN[1:]], "duration True is not a number of frames"),
    ([{**PLAN[0], "start": -1}, *PLAN[1:]], "start -1 is not a frame number"),
    ([{**PLAN[0], "start": None}, *PLAN[1:]], "start None is not a frame number"),
    ([PLAN[0], {**PLAN[1], "duration": 0}, PLAN[2]], "duration 0 is not a number of frames"),
    ([PLAN[0], {**PLAN[1], "start": 3}, PLAN[2]], "starts at frame 3, but the segment before it ends at frame 1"),
    ([PLAN[0], {**PLAN[1], "start": 1}, PLAN[2]], "starts at frame 1, but the segment before it ends at frame 1"),
    ([PLAN[0], PLAN[2]], "segment 1 is named 'segment_002', not segment_001"),
    ([PLAN[0], {**PLAN[1], "name": "../elsewhere"}, PLAN[2]], "is named '../elsewhere', not segment_001"),
    ([{**PLAN[0], "name": 0}, *PLAN[1:]], "segment 0 is named 0, not segment_000"),
    ([], "lists no segments"),
])
def test_a_video_json_that_is_not_consecutive_integer_segments_is_refused_by_name(tmp_path, segments, message):
    run = Run(tmp_path)
    run.write_video({"segment_frames": 2, "data_path": "x", "segments": segments})
    with pytest.raises(DataError, match=r"video\.json: .*" + message.replace("(", r"\(").replace(")", r"\)")):
        run.read_video()
    run.write_video({"segment_frames": 2, "data_path": "x", "segments": PLAN})
    assert run.read_video()["segments"] == PLAN


def test_a_resumed_video_refuses_a_video_json_that_moved_a_segment_s_frames(trained, tmp_path, capsys):
    """The reviewer's repro: segment_001 (frames 2-3) was killed; video.json edited to start it at frame 3 resumed
    it on frames 3-4 (its checkpoint's), frame 2 gone, and said "whole video written". A string duration failed
    with a TypeError traceback."""
    data, video = _copy(trained, tmp_path)
    second = Run(video / "segment_001")
    second.summary_path.unlink()  # killed: its checkpoint and saved model stay
    checkpoint = second.checkpoint_path.read_bytes()
    _write_segments(video, [PLAN[0], {**PLAN[1], "start": 3}, PLAN[2]])
    assert main(["train", str(data), "--out", str(video), "--resume", "--no-ray"]) == 2
    err = capsys.readouterr().err
    assert "video.json" in err and "segment 1 (segment_001): starts at frame 3" in err
    _write_segments(video, [*PLAN[:2], {**PLAN[2], "duration": "2"}])
    assert main(["train", str(data), "--out", str(video), "--resume", "--no-ray"]) == 2
    assert "video.json: segment 2 (segment_002): duration '2' is not a number" in capsys.readouterr().err
    _write_segments(video, SHIFTED)
    assert main(["train", str(data), "--out", str(video), "--resume", "--no-ray"]) == 2
    err = capsys.readouterr().err
    assert str(second.config_path) in err and "data.start=2, data.duration=2" in err and "start=2, duration=1" in err
    assert not second.training_finished() and second.checkpoint_path.read_bytes() == checkpoint
    # Put back, the video resumes as before.
    _write_segments(video, PLAN)
    assert main(["train", str(data), "--out", str(video), "--resume", "--no-ray"]) == 0
    assert second.training_finished() and second.read_config()["data"]["start"] == 2


def test_compress_refuses_a_bad_video_json_before_encoding_any_segment(trained, tmp_path, capsys, monkeypatch):
    """"start": "two" printed `invalid literal for int()`, without naming video.json, after encoding segment 0;
    frames that contradict a segment's config.json were packed into the container as they stood."""
    import stgc.codec.files as files

    _, video = _copy(trained, tmp_path)
    encoded = []
    encode = files._encode_model
    monkeypatch.setattr(files, "_encode_model", lambda source, *a: encoded.append(source) or encode(source, *a))
    bitstream = video / "v.stgc"
    _write_segments(video, [PLAN[0], {**PLAN[1], "start": "two"}, PLAN[2]])
    assert main(["compress", str(video), "--out", str(bitstream), *LADDER]) == 2
    assert "video.json: segment 1 (segment_001): start 'two' is not a frame number" in capsys.readouterr().err
    assert encoded == [] and not bitstream.exists()
    _write_segments(video, SHIFTED)
    assert main(["compress", str(video), "--out", str(bitstream), *LADDER]) == 2
    err = capsys.readouterr().err
    assert str(video / "segment_001" / "config.json") in err and "data.start=2, data.duration=2" in err
    assert encoded == [] and not bitstream.exists()
    # An unfinished segment is refused before the others are encoded, too.
    _write_segments(video, PLAN)
    (video / "segment_002" / Run.SUMMARY).unlink()
    assert main(["compress", str(video), "--out", str(bitstream), *LADDER]) == 2
    assert "segment_002: segment has not finished training" in capsys.readouterr().err
    assert encoded == [] and not bitstream.exists()


def test_a_restored_video_names_its_restored_from_json_when_video_json_contradicts_it(trained, tmp_path, capsys):
    """Restored without its run config, a segment's frames are in restored_from.json: packed again under an edited
    video.json, each model was given frames it was not trained on."""
    _, video = _copy(trained, tmp_path)
    bare = video / "bare.stgc"
    assert main(["compress", str(video), "--out", str(bare), *LADDER, "--set", "codec.embed_run_config=false"]) == 0
    restored = tmp_path / "restored"
    assert main(["decompress", str(bare), "--out", str(restored)]) == 0
    assert not (restored / "segment_001" / Run.CONFIG).exists()
    _write_segments(restored, SHIFTED)
    assert main(["compress", str(restored), "--out", str(restored / "again.stgc"), *LADDER]) == 2
    err = capsys.readouterr().err
    assert str(restored / "segment_001" / Run.RESTORED_FROM) in err and "start=2, duration=2" in err
    assert not (restored / "again.stgc").exists()


@pytest.mark.parametrize("embed", ["true", "false"])
def test_resuming_a_decompressed_video_says_it_is_a_restored_model_and_keeps_it(trained, tmp_path, capsys, embed):
    """It said the video's start "was killed before it saved its options" and to start it again with --overwrite,
    which removes the restored models."""
    data, video = _copy(trained, tmp_path)
    bitstream = video / "v.stgc"
    assert main(["compress", str(video), "--out", str(bitstream), *LADDER,
                 "--set", f"codec.embed_run_config={embed}"]) == 0
    restored = tmp_path / "dec1"
    assert main(["decompress", str(bitstream), "--out", str(restored)]) == 0
    models = sorted(p.relative_to(restored) for p in restored.rglob("point_cloud.ply"))
    assert len(models) == 3
    for extra in ([], ["--segment-frames", "2"]):
        assert main(["train", str(data), "--out", str(restored), "--resume", *extra, "--no-ray"]) == 2
        err = capsys.readouterr().err
        assert "restored from a bitstream (stgc decompress)" in err and "nothing to resume" in err
        assert "--overwrite" not in err.replace("--overwrite would remove", "")
    assert sorted(p.relative_to(restored) for p in restored.rglob("point_cloud.ply")) == models
    assert not any(restored.rglob(Run.CHECKPOINT))
