"""stgc.run.Run: the one owner of a run directory's layout."""

from __future__ import annotations

import json

import pytest

from stgc.errors import FormatError
from stgc.run import Run, RunExistsError


def _fake_run(path, iterations=(10, 200)):
    run = Run.create(path)
    run.write_config({"data": {"path": "somewhere"}, "model": {}, "train": {}, "compaction": None})
    for n in iterations:
        run.iteration_dir(n).mkdir(parents=True)
        (run.iteration_dir(n) / "point_cloud.ply").write_bytes(b"ply")
    return run


def test_run_is_found_from_anything_inside_it(tmp_path):
    run = _fake_run(tmp_path / "run")
    ply = run.iteration_dir(200) / "point_cloud.ply"
    for inside in (run.path, run.iteration_dir(200), ply):
        assert Run.of(inside) == run
    assert Run.of(tmp_path) is None


def test_latest_model_is_the_largest_iteration_that_holds_its_ply(tmp_path):
    run = _fake_run(tmp_path / "run", iterations=(9, 10, 200))
    run.iteration_dir(3000).mkdir(parents=True)  # an interrupted save: no PLY
    assert run.latest_model_dir() == run.iteration_dir(200)  # numeric, not lexicographic ("9" > "200")
    assert sorted(run.saved_iterations()) == [9, 10, 200]


def test_config_and_summary_round_trip_and_damage_is_named(tmp_path):
    run = _fake_run(tmp_path / "run")
    assert run.has_config() and run.read_config()["data"]["path"] == "somewhere"
    assert run.read_summary() is None and not run.training_finished()
    run.write_summary({"finished": True, "iterations": 5})
    assert run.training_finished()
    run.config_path.write_text("{not json")
    with pytest.raises(FormatError, match="config.json"):
        run.read_config()
    assert run.read_config(strict=False) is None


def test_evaluation_records_per_dataset_and_per_bitstream(tmp_path):
    run = Run(tmp_path)
    assert run.eval_paths() == (tmp_path / "eval.json", tmp_path / "eval_per_view.csv")
    assert run.eval_paths("other")[0] == tmp_path / "eval_on_other.json"
    assert run.eval_paths(bitstream=tmp_path / "m.stgc")[0] == tmp_path / "eval_m.json"
    assert run.eval_paths("other", tmp_path / "m.stgc")[0] == tmp_path / "eval_m_on_other.json"
    (tmp_path / "eval.json").write_text(json.dumps({"psnr": 30.0}))
    assert run.read_eval() == {"psnr": 30.0} and run.read_eval("other") is None


def test_create_refuses_an_existing_run_and_overwrite_clears_it(tmp_path):
    run = _fake_run(tmp_path / "run")
    (run.path / "model_q3.stgc").write_bytes(b"x")  # derived from the old model
    # The experiment runner's label of the old run: kept, the report named the new run after the old plan entry.
    (run.path / "experiment.json").write_text(json.dumps({"family": "ST-KNN", "label": "Case 2"}))
    (run.path / "notes.txt").write_text("mine")
    with pytest.raises(RunExistsError, match="--overwrite"):
        Run.create(run.path)
    fresh = Run.create(run.path, overwrite=True)
    assert not fresh.has_config() and fresh.latest_model_dir() is None
    assert not (run.path / "model_q3.stgc").exists() and not (run.path / "experiment.json").exists()
    assert (run.path / "notes.txt").read_text() == "mine"


def test_progress_reads_the_files_of_a_run_training_elsewhere(tmp_path):
    run = Run(tmp_path / "r")
    assert run.progress() == (0, 0)  # nothing written yet
    run.path.mkdir()
    run.write_config({"train": {"iterations": 300}})
    assert run.progress() == (0, 300)
    # The last complete row counts; a row still being written is skipped.
    (run.path / Run.METRICS).write_text('{"iteration": 50}\n{"iteration": 100}\n{"iterat')
    assert run.progress() == (100, 300)
    run.write_summary({"finished": True})
    assert run.progress() == (300, 300)


def test_a_whole_video_description_without_its_segment_length_is_refused_by_name(tmp_path):
    """A video.json without segment_frames passed the check and a resume failed on it with a KeyError traceback."""
    from stgc.errors import StgcError
    from stgc.run import Run

    run = Run(tmp_path)
    segments = [{"name": "segment_000", "start": 0, "duration": 2}]
    for frames in (None, 0, True, "2"):
        video = {"data_path": "x", "segments": segments} | ({} if frames is None else {"segment_frames": frames})
        run.write_video(video)
        with pytest.raises(StgcError, match=r"video.json: not a whole-video description \(segment_frames >= 1"):
            run.read_video()
    run.write_video({"segment_frames": 2, "data_path": "x", "segments": segments})
    assert run.read_video()["segment_frames"] == 2
